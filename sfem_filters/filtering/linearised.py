"""A model linearised about a trajectory: the linear-Gaussian problem of one Gauss-Newton step.

About a trajectory ``z_t = [r_t; theta]`` (restart part r, static parameters theta), a model's
transition is replaced by its first-order expansion (Eqs. 31-33) and the restart part is
written in coordinates xi of the linearisation's choice, ``r = V xi``:

    xi_{t+1} = A_t xi_t + M_t (theta - theta_bar) + c_t + w_t,     w_t ~ N(0, s_t Q)
    y_t      = H xi_t + v_t,                                      v_t ~ N(0, R_t)
    xi_0 ~ N(xi0, P0),   theta ~ N(theta0, P_theta0),   independent (Eq. 34)

A model that knows coordinates in which ``A`` is sparse offers them through
:class:`sfem_filters.filtering.protocol.Linearisable` (the SFEM model uses its vibration modes:
A is then block-diagonal with 2 x 2 blocks and a time update costs O(n^2 p), not O(n^3));
:func:`linearise` falls back to the dense Jacobians ``F_jacobian`` in the model's own
coordinates (``V = I``) for any other model of the contract.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._validate import as_float_array
from .protocol import Linearisable, check_model, measurement_cov, n_parameters, process_profile

__all__ = ["LinearisedModel", "linearise", "linearise_dense", "check_static_parameters"]


@dataclass(eq=False)
class LinearisedModel:
    """The linear-Gaussian model of one Gauss-Newton step (see the module docstring).

    Attributes
    ----------
    A : (n_r, n_r) sparse or dense array, or a list of ``n_frames - 1`` of them
        Transition of the restart part in the coordinates xi.
    M : (n_frames - 1, n_r, p) array
        Sensitivities ``d r_{t+1} / d theta`` at the trajectory (Eq. 33), in xi coordinates.
    c : (n_frames - 1, n_r) array
        Offsets: the transition of the trajectory's own state is ``A_t xi_t + c_t``.
    H : (m, n_r) array
        Observation of the restart part (the observation does not see theta).
    R : (n_frames, m, m) array
        Measurement noise covariance of every frame.
    Q : (n_r, n_r) array
        Process noise of the restart part per frame (theta is static); interval t's is :meth:`Q_at`.
    xi0, P0 : (n_r,), (n_r, n_r) arrays
        Prior of the first frame's restart part.
    theta_bar, theta0 : (p,) arrays
        The parameters of the linearisation, and their prior mean.
    P_theta0 : (p, p) array
        Their prior covariance.
    V : (n_r, n_r) array or sparse matrix, or None
        Model coordinates of xi, ``r = V xi`` (None: the identity).
    q_scale : (n_frames - 1,) array or None
        Factor ``s_t`` on Q of the interval from frame t to t + 1 (the model's
        :class:`~sfem_filters.filtering.protocol.ProcessNoiseProfile`); None: 1 every interval.
    """

    A: object
    M: np.ndarray
    c: np.ndarray
    H: np.ndarray
    R: np.ndarray
    Q: np.ndarray
    xi0: np.ndarray
    P0: np.ndarray
    theta_bar: np.ndarray
    theta0: np.ndarray
    P_theta0: np.ndarray
    V: object = None
    q_scale: object = None

    @property
    def n_frames(self) -> int:
        """Number of frames (one R per frame)."""
        return len(self.R)

    @property
    def n_restart(self) -> int:
        """Size n_r of the restart part xi."""
        return len(self.xi0)

    @property
    def n_params(self) -> int:
        """Number p of static parameters theta."""
        return len(self.theta0)

    @property
    def dim_state(self) -> int:
        """Size of the state ``[xi; theta]``: n_r + p."""
        return self.n_restart + self.n_params

    @property
    def dim_obs(self) -> int:
        """Number m of observations per frame (rows of H)."""
        return self.H.shape[0]

    def Q_at(self, t: int) -> np.ndarray:
        """Process noise of the interval from frame ``t`` to ``t + 1``: ``s_t Q`` (``Q`` without a profile)."""
        return self.Q if self.q_scale is None else self.q_scale[t] * self.Q

    def A_at(self, t: int):
        """Transition from frame ``t`` to ``t + 1``."""
        return self.A[t] if isinstance(self.A, list) else self.A

    def to_model(self, xi) -> np.ndarray:
        """Restart state(s) in model coordinates, ``V xi`` (xi of shape (..., n_r))."""
        xi = np.asarray(xi, float)
        if self.V is None:
            return xi.copy()
        return np.asarray((self.V @ xi.reshape(-1, self.n_restart).T).T).reshape(xi.shape)

    def output_in_xi(self, L) -> np.ndarray:
        """An output operator ``L`` on the restart part in model coordinates as one on xi: ``L V``."""
        L = L.toarray() if sp.issparse(L) else np.asarray(L, float)
        return L if self.V is None else np.asarray(L @ self.V)


def check_static_parameters(model) -> int:
    """Check that the parameters are static (zero process noise, identity transition rows) and
    independent of the restart part a priori (Eq. 34); returns their number p."""
    nr, p = int(model.n_restart), n_parameters(model)
    Q = np.asarray(model.Q, float)
    P0 = np.asarray(model.P0, float)
    if p and np.any(Q[nr:, :] != 0):
        raise ValueError("model: expected static parameters (zero process noise on theta) for the smoother, got a "
                         "non-zero Q on theta (material_process_std > 0?)")
    if p and np.any(P0[:nr, nr:] != 0):
        raise ValueError("model: expected a prior without cross-covariance between the state and theta (Eq. 34)")
    return p


def _check_states(model, states) -> np.ndarray:
    z = as_float_array("states", states, shape=(model.n_frames, model.dim_state))
    nr = model.n_restart
    if n_parameters(model) and np.any(z[:, nr:] != z[:1, nr:]):
        raise ValueError("states: expected one value of theta along the trajectory (static parameters)")
    return z


def linearise_dense(model, states, sensitivity: bool = True) -> LinearisedModel:
    """The generic linearisation: ``F_jacobian`` and ``fx`` at every frame, model coordinates.

    Works for any :class:`sfem_filters.filtering.protocol.FilterModel` whose observation is
    linear in the restart part (``hx(z) = H z`` with H zero on theta) and whose parameters are
    static. Costs one dense Jacobian per frame. ``sensitivity=False`` gives the model at the
    trajectory's theta with theta fixed (no parameters in the state: ``p = 0``).
    """
    check_model(model)
    check_static_parameters(model)
    z = _check_states(model, states)
    nr, T = int(model.n_restart), int(model.n_frames)
    H = np.asarray(model.H_jacobian(z[0], 0), float)
    if np.any(H[:, nr:] != 0) or not np.allclose(model.hx(z[0], 0), H @ z[0], rtol=1e-12, atol=0):
        raise ValueError("model: expected a linear observation of the state (hx(z) = H z, H zero on theta) "
                         "for the smoother")
    p = n_parameters(model) if sensitivity else 0
    A, M, c = [], np.empty((T - 1, nr, p)), np.empty((T - 1, nr))
    for t in range(T - 1):
        F = np.asarray(model.F_jacobian(z[t], t), float)
        if np.any(F[nr:, :nr] != 0) or np.any(F[nr:, nr:] != np.eye(F.shape[0] - nr)):
            raise ValueError("model: expected static parameters (F = [[A, M_t], [0, I]]) for the smoother")
        A.append(F[:nr, :nr])
        M[t] = F[:nr, nr:nr + p]
        c[t] = np.asarray(model.fx(z[t], t), float).ravel()[:nr] - F[:nr, :nr] @ z[t, :nr]
    Q, P0 = np.asarray(model.Q, float), np.asarray(model.P0, float)
    theta = z[0, nr:nr + p]
    return LinearisedModel(A=A, M=M, c=c, H=H[:, :nr], R=np.array([measurement_cov(model, t) for t in range(T)]),
                           Q=Q[:nr, :nr], xi0=np.asarray(model.x0, float)[:nr].copy(), P0=P0[:nr, :nr],
                           theta_bar=theta.copy(), theta0=np.asarray(model.x0, float)[nr:nr + p].copy(),
                           P_theta0=P0[nr:nr + p, nr:nr + p], V=None, q_scale=process_profile(model))


def linearise(model, states, sensitivity: bool = True) -> LinearisedModel:
    """The model's own :class:`~sfem_filters.filtering.protocol.Linearisable` linearisation about
    ``states`` (n_frames, dim_state), or :func:`linearise_dense`. With ``sensitivity=False``
    theta is held at the trajectory's (``p = 0``): the exact linear model of that material."""
    if isinstance(model, Linearisable):
        _check_states(model, states)
        return model.linearise(states, sensitivity=sensitivity)
    return linearise_dense(model, states, sensitivity)
