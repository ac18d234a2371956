"""The model in filterpy's own ``UnscentedKalmanFilter`` (Merwe scaled sigma points).

:func:`make_ukf` hands the model's ``fx`` and ``hx`` to filterpy unchanged (filterpy calls
``fx(x, dt, **fx_args)`` and ``hx(x, **hx_args)``; the frame index travels as ``t``)::

    ukf = make_ukf(model)
    for t, y in enumerate(observations):
        if t > 0:
            ukf.predict(t=t - 1)                  # frame t-1 -> t through model.fx
        ukf.update(y, t=t)

2n + 1 sigma points, each propagated through the exact transition: a full-state UKF is for
small meshes. :class:`UKFEngine` runs it in the engine interface (``engine="ukf"`` of the
cyclic driver). For a model linear in the state (material fixed) it is the Kalman filter.
"""
from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from .base import Engine
from .protocol import measurement_cov

__all__ = ["make_ukf", "UKFEngine"]


def make_ukf(model, alpha: float = 1.0, beta: float = 2.0, kappa: float = 0.0) -> UnscentedKalmanFilter:
    """filterpy's ``UnscentedKalmanFilter`` on ``model`` with its x0, P0, Q and R.

    Parameters
    ----------
    model : :class:`~sfem_filters.filtering.protocol.FilterModel`
    alpha, beta, kappa : float
        Merwe's scaled sigma-point parameters (filterpy's ``MerweScaledSigmaPoints``); the
        default ``alpha = 1`` keeps the weights positive-definite for large states.
    """
    if not 0 < alpha <= 1:
        raise ValueError(f"alpha: expected a spread in (0, 1], got {alpha!r}")
    n = int(model.dim_state)
    points = MerweScaledSigmaPoints(n, alpha=alpha, beta=beta, kappa=kappa)
    ukf = UnscentedKalmanFilter(dim_x=n, dim_z=int(model.dim_obs), dt=1.0,
                                fx=lambda x, dt, t: model.fx(x, t), hx=lambda x, t=None: model.hx(x, t),
                                points=points)
    ukf.x = np.array(model.x0, float)
    ukf.P = np.array(model.P0, float)
    ukf.Q = np.array(model.Q, float)
    ukf.R = np.array(model.R, float)
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)   # so that an update may come first (frame 0)
    return ukf


class UKFEngine(Engine):
    """filterpy's UKF (:func:`make_ukf`) in the engine interface; NaN rows are left out of an
    update through ``hx`` and ``R`` restricted to the observed rows."""

    supports_ljung = False

    def __init__(self, model, ljung: bool = False):
        if ljung:
            raise ValueError("ljung: the unscented filter has no tangent operator for Ljung's term (use ljung=False)")
        super().__init__(model, ljung=False)
        self.ukf = make_ukf(model)

    def reset(self, x, P) -> None:
        self.ukf.x = np.asarray(x, float).ravel().copy()
        P = np.asarray(P, float)
        self.ukf.P = 0.5 * (P + P.T)
        self.ukf.sigmas_f = self.ukf.points_fn.sigma_points(self.ukf.x, self.ukf.P)

    @property
    def x(self) -> np.ndarray:
        return self.ukf.x

    @property
    def P(self) -> np.ndarray:
        return self.ukf.P

    def predict(self, t: int) -> None:
        self.ukf.predict(t=t)

    def update(self, y, t: int, mask) -> tuple:
        m = self.model
        R = measurement_cov(m, t)[np.ix_(mask, mask)]
        self.ukf.update(np.asarray(y, float)[mask], R=R, hx=lambda x, t: m.hx(x, t)[mask], t=t)
        self.ukf.P = 0.5 * (self.ukf.P + self.ukf.P.T)
        return self.ukf.y.ravel(), self.ukf.S
