"""The reduced-order unscented Kalman filter of Moireau & Chapelle (2011): the field's standard
for material parameters in large cardiac models, in the engine interface.

Moireau, P. & Chapelle, D. (2011) Reduced-order Unscented Kalman Filtering with application to
parameter identification in large-dimensional systems. ESAIM: COCV 17, 380-405,
doi:10.1051/cocv/2010006 (section 2, the discrete-time reduced-order UKF with simplex sigma
points); as implemented in Verdandi's ``ReducedOrderUnscentedKalmanFilter`` and SOFA Optimus'
``ROUKFilter``. The equations below are those the code runs (the paper's own numbering is not
reproduced here).

The covariance of the state ``z = [x; theta]`` is kept in factored form of rank p (the number
of parameters)::

    P = L U^-1 L^T,        L: (n, p),  U: (p, p)

Simplex sigma points: p + 1 directions ``I_i`` in R^p with weights ``alpha = 1/(p+1)``,
``sum_i alpha I_i = 0`` and ``sum_i alpha I_i I_i^T = I_p`` (a regular simplex,
:func:`simplex_points`); ``[I]`` is the (p, p+1) matrix of them, ``D = alpha I_{p+1}``.

Sampling (before each step), with ``C C^T = U^-1`` (Cholesky)::

    z_i = z + L C I_i,                            i = 1 .. p+1

Prediction, each sigma point through the model's exact transition (no tangent operator)::

    z_i^- = f(z_i),   z^- = sum_i alpha z_i^-,   L^- = [z_i^-] D [I]^T,   U^- = I_p

Correction, with the observations of the sigma points and ``W`` the measurement covariance::

    Y_i = h(z_i),   Y = sum_i alpha Y_i,   HL = [Y_i] D [I]^T
    U^+ = I_p + HL^T W^-1 HL
    z^+ = z + L U^+^-1 HL^T W^-1 (y - Y)          (the kinematics corrected by the same gain)

with ``L`` the sampled factor ``L C``. For a model linear in z this is the Kalman filter of a
covariance of rank p exactly. What the reduced order leaves out: process noise ``Q`` (the
uncertainty lives in the parameters only, as in the paper) and any part of the initial
kinematic covariance not explained by the parameters; :meth:`ROUKFEngine.reset` keeps of a full
``P`` exactly its parameter block and the kinematics' regression on the parameters.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from .base import Engine
from .protocol import measurement_cov

__all__ = ["ROUKFEngine", "simplex_points"]


def simplex_points(p: int) -> np.ndarray:
    """(p, p+1) directions of the regular simplex sigma points, ``sum_i I_i = 0`` and
    ``sum_i I_i I_i^T / (p+1) = I_p``."""
    if p < 1:
        raise ValueError(f"p: expected at least one parameter, got {p}")
    E = np.eye(p + 1) - 1.0 / (p + 1)               # centred basis vectors of R^{p+1}
    Qb = np.linalg.svd(E)[0][:, :p]                  # orthonormal basis of the hyperplane sum = 0
    return np.sqrt(p + 1) * (Qb.T @ E)


class ROUKFEngine(Engine):
    """The reduced-order UKF (module docstring) as an engine of the cyclic driver.

    ``P`` is formed on demand as ``L U^-1 L^T`` (rank p, so not positive definite): the
    safeguards' positive-definiteness check asks :meth:`cholesky`, which answers for ``U``.
    Ljung's term needs a tangent operator, which this filter has none of.
    """

    supports_ljung = False

    def __init__(self, model, ljung: bool = False):
        if ljung:
            raise ValueError("ljung: the reduced-order UKF has no tangent operator for Ljung's term (use ljung=False)")
        super().__init__(model, ljung=False)
        self.nx = int(model.n_restart)
        self.p = int(model.dim_state) - self.nx
        if self.p < 1:
            raise ValueError("model: the reduced-order UKF estimates parameters; this model has none "
                             "(use a material-estimating configuration)")
        self.I = simplex_points(self.p)
        self.alpha = 1.0 / (self.p + 1)

    def reset(self, x, P) -> None:
        x = np.asarray(x, float).ravel()
        P = np.asarray(P, float)
        nx = self.nx
        Ptt = 0.5 * (P[nx:, nx:] + P[nx:, nx:].T)
        self._z = x.copy()
        self._L = np.vstack([np.linalg.solve(Ptt, P[nx:, :nx]).T, np.eye(self.p)])
        self._U = np.linalg.inv(Ptt)
        self._U = 0.5 * (self._U + self._U.T)

    @property
    def x(self) -> np.ndarray:
        return self._z

    @property
    def P(self) -> np.ndarray:
        LC = self._sqrt()
        return LC @ LC.T

    def cholesky(self):
        """Cholesky factor of ``U`` (the reduced covariance's information), or None if ``U`` is
        not positive definite."""
        try:
            return np.linalg.cholesky(self._U)
        except np.linalg.LinAlgError:
            return None

    def _sqrt(self) -> np.ndarray:
        """``L C`` with ``C C^T = U^-1``: a square root of P, (n, p)."""
        C = np.linalg.cholesky(np.linalg.inv(self._U))
        return self._L @ C

    def _sigma(self) -> tuple:
        LC = self._sqrt()
        return self._z[:, None] + LC @ self.I, LC

    def predict(self, t: int) -> None:
        Z, _ = self._sigma()
        Zf = np.column_stack([np.asarray(self.model.fx(Z[:, i], t), float).ravel() for i in range(self.p + 1)])
        self._z = Zf.mean(axis=1)
        self._L = self.alpha * Zf @ self.I.T
        self._U = np.eye(self.p)

    def update(self, y, t: int, mask) -> tuple:
        Z, LC = self._sigma()
        Y = np.column_stack([np.asarray(self.model.hx(Z[:, i], t), float).ravel()[mask]
                             for i in range(self.p + 1)])
        W = measurement_cov(self.model, t)[np.ix_(mask, mask)]
        HL = self.alpha * Y @ self.I.T
        e = np.asarray(y, float)[mask] - Y.mean(axis=1)
        cW = sla.cho_factor(W)
        WiHL = sla.cho_solve(cW, HL)
        U = np.eye(self.p) + HL.T @ WiHL
        U = 0.5 * (U + U.T)
        self._z = self._z + LC @ np.linalg.solve(U, WiHL.T @ e)
        self._L, self._U = LC, U
        S = HL @ HL.T + W
        return e, 0.5 * (S + S.T)
