"""filterpy's ExtendedKalmanFilter driven by a model: the reference engine.

:class:`SFEMExtendedKalmanFilter` is filterpy's EKF with the state propagated by the model's
exact transition ``fx`` (Eq. 19) instead of ``F x``; :class:`FilterpyEngine` runs it in the
engine interface (:class:`sfem_filters.filtering.base.Engine`).
"""
from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from .base import Engine
from .protocol import measurement_cov

__all__ = ["SFEMExtendedKalmanFilter", "FilterpyEngine"]


class SFEMExtendedKalmanFilter(ExtendedKalmanFilter):
    """filterpy's EKF driven by an SFEM model.

    Only ``predict_x`` differs from filterpy: it sets ``F`` from ``model.F_jacobian`` at the
    current state and propagates the state with ``model.fx`` (the exact nonlinear transition
    of Eq. 19), instead of ``F @ x``. ``predict(u=t)`` steps from frame t to t + 1.
    """

    def __init__(self, model):
        super().__init__(dim_x=model.dim_state, dim_z=model.dim_obs)
        self.model = model
        self.x = np.asarray(model.x0, float).reshape(-1, 1).copy()
        self.P = np.array(model.P0, float)
        self.Q = np.array(model.Q, float)
        self.R = np.array(model.R, float)
        self.jacobian = model.F_jacobian      # (z, t) -> F; LjungCoupling replaces it

    def predict_x(self, u=0):
        """Propagate x from frame ``u`` (an int) to frame ``u + 1`` and set F there."""
        t = int(u)
        self.F = self.jacobian(self.x, t)
        self.x = self.model.fx(self.x, t)

    def predict_update(self, z, HJacobian, Hx, args=(), hx_args=(), u=0):
        """``predict(u)`` then ``update(z, ...)``: filterpy's own version would use F x, not fx."""
        self.predict(u)
        self.update(z, HJacobian, Hx, args=args, hx_args=hx_args)


class FilterpyEngine(Engine):
    """Runs the filter through :class:`SFEMExtendedKalmanFilter` (the reference)."""

    def __init__(self, model, ljung: bool = False):
        super().__init__(model, ljung)
        self.ekf = model.make_ekf()
        self.ekf.jacobian = self._jacobian

    def reset(self, x, P):
        self.ekf.x = np.asarray(x, float).reshape(-1, 1).copy()
        self.ekf.P = np.array(P, float)
        if self.ljung is not None:
            self.ljung.reset(self.ekf.P)

    @property
    def x(self):
        return self.ekf.x.ravel()

    @property
    def P(self):
        return self.ekf.P

    def predict(self, t):
        self.ekf.predict(u=t)

    def update(self, y, t, mask):
        m = self.model
        H = m.H_jacobian(self.ekf.x, t)[mask]
        R = measurement_cov(m, t)[np.ix_(mask, mask)]
        self.ekf.update(y[mask].reshape(-1, 1), lambda x, tt: H,
                        lambda x, tt: m.hx(x, tt)[mask], R=R, args=t, hx_args=t)
        e = self.ekf.y.ravel()
        self._observed(H, R, e)
        return e, self.ekf.S
