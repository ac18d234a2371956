"""Ljung's (1979) modification of the coupling term of the joint EKF (paper Eq. 40)."""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from .protocol import TransitionDerivatives

__all__ = ["LjungCoupling", "LJUNG_MAX_PARAMS"]


#: Ljung's gain sensitivities cost one Riccati derivative per parameter per frame.
LJUNG_MAX_PARAMS = 16


class LjungCoupling:
    """Ljung's (1979) modification of the coupling term of the joint EKF (paper Eq. 40).

    Written in predictor form, one frame of the joint EKF moves the kinematic (restart) state
    by ``x_{t+1|t} = A(theta) [x_{t|t-1} + K_t(theta) e_t] + B(theta) w_t`` with the
    innovation ``e_t = y_t - H x_{t|t-1}``. The plain EKF differentiates this map with respect
    to theta as if the gain did not depend on theta; Ljung showed that this biases the
    parameter estimate whenever it does (for example when a parameter couples noise into the
    state) and that adding the gain derivative turns the EKF into a recursive prediction-error
    method. In the filter (update-then-predict) form used here, ``M_t`` is evaluated at the
    posterior ``x_{t|t} = x_{t|t-1} + K_t e_t`` and so already holds ``dA/dtheta K_t e_t``;
    the modification adds the remaining term to the parameter columns of ``F_t``::

        F_t = [[A, M_t + A [dK_t/dtheta_1 e_t, ..., dK_t/dtheta_p e_t]], [0, I]].

    ``K_t(theta)`` is the Kalman gain of the restart block for a known theta, from the
    Riccati recursion ``Pi_{t+1} = A (I - K_t H) Pi_t A^T + Q``, ``K_t = Pi_t H^T S_t^-1``,
    ``S_t = H Pi_t H^T + R``. Its derivative comes from the sensitivity recursion, with
    ``Pi'`` = dPi/dtheta_i and ``A'`` = dA/dtheta_i (Q and R independent of theta)::

        K'_t = (I - K_t H) Pi'_t H^T S_t^-1
        Pi'_{t|t} = (I - K_t H) Pi'_t (I - K_t H)^T
        Pi'_{t+1} = A' Pi_{t|t} A^T + A Pi_{t|t} A'^T + A Pi'_{t|t} A^T.

    Pi restarts from the restart block of P with Pi' = 0 (every cyclic loop). The model
    supplies ``transition_derivatives(z, t)``: dA/dtheta_i of the restart block, shape
    (p, n_restart, n_restart). Cost per frame: O(p n^3); p is limited to
    :data:`LJUNG_MAX_PARAMS` (use a region or basis parameterisation for more elements).
    """

    def __init__(self, model):
        nr, p = model.n_restart, model.dim_state - model.n_restart
        if p == 0:
            raise ValueError("ljung: expected a model that estimates parameters (theta in the state), "
                             "got one with none; Ljung's term only changes the parameter columns of F")
        if p > LJUNG_MAX_PARAMS:
            raise ValueError(f"ljung: expected at most {LJUNG_MAX_PARAMS} estimated parameters (the gain "
                             f"sensitivities cost one Riccati derivative each), got {p}; use a per-region "
                             "or basis parameterisation")
        if not isinstance(model, TransitionDerivatives):
            raise TypeError("ljung: expected a model with transition_derivatives(z, t) "
                            f"(dA/dtheta), got a {type(model).__name__} without it")
        self.model = model
        self.nr, self.p = nr, p
        self.Pi = np.zeros((nr, nr))
        self.dPi = np.zeros((p, nr, nr))
        self._post = None

    def reset(self, P):
        """Restart the Riccati recursion from the restart block of P (dPi/dtheta = 0)."""
        self.Pi = np.array(P[: self.nr, : self.nr], float)
        self.dPi = np.zeros((self.p, self.nr, self.nr))
        self._post = None

    def after_update(self, H, R, innovation):
        """Measurement step of the Riccati recursion and its derivative.

        ``H`` (m, dim_state) and ``R`` (m, m) are the observed rows of the frame and
        ``innovation`` their ``y_t - h(x_{t|t-1})`` (m of them, possibly none). Stores the
        posterior Pi, dPi and the columns ``dK/dtheta_i e_t``, shape (n_restart, p).
        """
        H = np.asarray(H, float)[:, : self.nr]
        if H.shape[0] == 0:
            self.gain_derivative = np.zeros((self.p, self.nr, 0))
            self._post = (self.Pi, self.dPi, np.zeros((self.nr, self.p)))
            return
        PHt = self.Pi @ H.T
        cho = sla.cho_factor(H @ PHt + R, lower=True)
        K = sla.cho_solve(cho, PHt.T).T
        IKH = np.eye(self.nr) - K @ H
        dK = np.stack([IKH @ sla.cho_solve(cho, (dP @ H.T).T).T for dP in self.dPi])  # (p, nr, m)
        self.gain = K
        self.gain_derivative = dK
        Pi_post = IKH @ self.Pi
        Pi_post = 0.5 * (Pi_post + Pi_post.T)
        dPi_post = np.einsum("ab,pbc,dc->pad", IKH, self.dPi, IKH)
        self._post = (Pi_post, dPi_post, (dK @ np.asarray(innovation, float)).T)

    def coupling(self, z, t, A):
        """The extra columns ``A dK/dtheta e_t`` of F (n_restart, p), and the time step of the
        Riccati recursion and its sensitivity from frame t to t + 1."""
        if self._post is None:        # predict without update: nothing observed at frame t
            self.after_update(np.zeros((0, self.nr)), np.zeros((0, 0)), np.zeros(0))
        Pi, dPi, dKe = self._post
        dA = np.asarray(self.model.transition_derivatives(z, t), float)
        Qr = np.asarray(self.model.Q, float)[: self.nr, : self.nr]
        APi = A @ Pi
        new = APi @ A.T + Qr
        self.Pi = 0.5 * (new + new.T)
        d = np.einsum("pab,bc->pac", dA, APi.T) + np.einsum("ab,pcb->pac", APi, dA) \
            + np.einsum("ab,pbc,dc->pad", A, dPi, A)
        self.dPi = 0.5 * (d + d.transpose(0, 2, 1))
        self._post = None
        return A @ dKe

    def jacobian(self, z, t):
        """F_t of the model with Ljung's term added to its parameter columns."""
        z = np.asarray(z, float)
        F = np.array(self.model.F_jacobian(z, t), float)
        F[: self.nr, self.nr:] += self.coupling(z.ravel(), t, F[: self.nr, : self.nr])
        return F
