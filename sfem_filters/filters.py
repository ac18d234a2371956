"""Filtering with a model object: the filterpy plug-in and cyclic (periodic) estimation.

This module knows nothing of meshes: it talks to a model through ``fx``, ``F_jacobian``,
``hx``, ``H_jacobian``, ``Q``, ``R``, ``x0``, ``P0``, ``n_restart`` (the leading part of the
state restarted every loop: kinematics and effect states), ``dim_state``, ``dim_obs``,
``n_frames``, ``estimates_material`` and ``material_of_theta``.

Two engines run the same filter:

* ``"filterpy"``: :class:`SFEMExtendedKalmanFilter`, filterpy's ``ExtendedKalmanFilter``
  with ``predict_x`` routed through the model's exact transition. The reference.
* ``"structured"``: the same equations using F = [[A, M_t], [0, I]] block by block and a
  Cholesky solve instead of ``inv(S)``; Joseph-form update as in filterpy.
* ``"ud"``: the U-D factorised (Bierman-Thornton) filter, P = U D U^T with U unit upper
  triangular and D >= 0 by construction (section 2.8): Thornton's modified weighted
  Gram-Schmidt time update and Bierman's scalar measurement update.

Each engine takes ``ljung=True`` for Ljung's (1979) modification of the coupling term (Eq. 40),
see :class:`LjungCoupling`.
"""
from __future__ import annotations

import hashlib
import os
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.linalg.blas as blas
import scipy.sparse as sp
from filterpy.kalman import ExtendedKalmanFilter

from ._validate import as_float_array, integer, non_negative, probability
from .observations import LinearObservation

CHECKPOINT_FORMAT = 2


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
        if not callable(getattr(model, "transition_derivatives", None)):
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
        Qr = self.model.Q[: self.nr, : self.nr]
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


class _Engine:
    """Shared parts of the engines: the optional Ljung term."""

    def __init__(self, model, ljung: bool = False):
        self.model = model
        self.ljung = LjungCoupling(model) if ljung else None

    def _jacobian(self, z, t):
        if self.ljung is not None:
            return self.ljung.jacobian(z, t)
        return self.model.F_jacobian(z, t)

    def _observed(self, H, R, innovation):
        if self.ljung is not None:
            self.ljung.after_update(H, R, innovation)

    def cholesky(self):
        """Lower Cholesky factor of the current P, or None if P is not positive definite."""
        try:
            return np.linalg.cholesky(0.5 * (self.P + self.P.T))
        except np.linalg.LinAlgError:
            return None


class FilterpyEngine(_Engine):
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


def measurement_cov(model, t: int) -> np.ndarray:
    """R of frame ``t``: ``model.R_at(t)`` when the model has per-frame noise, else ``model.R``."""
    R_at = getattr(model, "R_at", None)
    return np.asarray(model.R if R_at is None else R_at(t), float)


def joseph_update(P, K, PHt, S) -> np.ndarray:
    """Joseph form ``(I - K H) P (I - K H)^T + K R K^T`` in O(n^2 m), exactly symmetric.

    Expanded, it is ``P - K (P H^T)^T - (P H^T) K^T + K S K^T`` with ``S = H P H^T + R``
    (for any gain K, not only the optimal one), that is ``P + X + X^T`` with
    ``X = K (K S / 2 - P H^T)^T``: one n x m by m x n product.

    Parameters
    ----------
    P : (n, n) symmetric array
    K : (n, m) array
        Gain.
    PHt : (n, m) array
        ``P H^T``.
    S : (m, m) array
        ``H P H^T + R``.
    """
    X = K @ (K @ (0.5 * S) - PHt).T
    out = X + X.T                 # exactly symmetric; P is too, so the sum stays so
    out += P
    return out


def _propagate_kinematic(A, Mt, P, L, nx: int) -> np.ndarray:
    """Kinematic block of ``F P F^T`` for F = [[A, Mt], [0, I]], (nx, nx).

    With the lower Cholesky factor ``L`` of P it is ``G G^T``, ``G = [A L_xx + Mt L_tx,
    Mt L_tt]``: ``A L_xx`` is a triangular product (BLAS trmm, on the transposes so that
    numpy's row-major arrays are LAPACK's column-major ones) and ``G G^T`` a symmetric
    product (numpy calls syrk for ``X @ X.T``). Without a factor (``L`` None: P not
    positive definite) it is the plain ``A P_xx A^T + A P_xt Mt^T + (.)^T + Mt P_tt Mt^T``.
    """
    if L is None:
        Pxx, Pxt, Ptt = P[:nx, :nx], P[:nx, nx:], P[nx:, nx:]
        APM = (A @ Pxt) @ Mt.T
        out = A @ Pxx @ A.T + APM + APM.T + Mt @ Ptt @ Mt.T
        return 0.5 * (out + out.T)
    G1 = blas.dtrmm(1.0, L[:nx, :nx].T, A.T, side=0, lower=0).T      # A L_xx (C-contiguous)
    if Mt.shape[1]:
        G1 += Mt @ L[nx:, :nx]
        Gt = Mt @ L[nx:, nx:]
        return G1 @ G1.T + Gt @ Gt.T
    return G1 @ G1.T


class StructuredEngine(_Engine):
    """The same filter exploiting F = [[A, M_t], [0, I]] and Cholesky factors of P and S.

    The time update propagates the factor ``P = L L^T``: with ``G = [A L_xx + M_t L_tx,
    M_t L_tt]`` the kinematic block is ``G G^T`` (one triangular product and one symmetric
    rank-n product, half the flops of ``A P_xx A^T``), the cross block ``A P_xt + M_t P_tt``,
    and the material block is unchanged. The factor is the one :class:`Safeguards` computes to
    check P after every step (:meth:`cholesky` caches it), so the check costs no extra work.
    """

    def __init__(self, model, ljung: bool = False):
        super().__init__(model, ljung)
        self.reset(model.x0, model.P0)

    def reset(self, x, P):
        self._x = np.asarray(x, float).ravel().copy()
        P = np.asarray(P, float)
        self._set_P(0.5 * (P + P.T))       # the steps keep it exactly symmetric from here on
        if self.ljung is not None:
            self.ljung.reset(self._P)

    def _set_P(self, P):
        self._P = P
        self._L = None          # Cholesky factor of P, computed on demand

    @property
    def x(self):
        return self._x

    @property
    def P(self):
        return self._P

    def cholesky(self):
        """Lower Cholesky factor of the current P (cached), or None if P is not positive definite."""
        if self._L is None:
            try:
                self._L = np.linalg.cholesky(self._P)      # exactly symmetric (see reset)
            except np.linalg.LinAlgError:
                self._L = False
        return None if self._L is False else self._L

    def predict(self, t):
        m = self.model
        nx = m.n_restart        # F = [[A', M'], [0, I]] with A' over kinematics and effect states
        F = self._jacobian(self._x, t)
        A, Mt = F[:nx, :nx], F[:nx, nx:]
        P = self._P
        Pxt, Ptt = P[:nx, nx:], P[nx:, nx:]
        new = np.empty_like(P)
        new[:nx, :nx] = _propagate_kinematic(A, Mt, P, self.cholesky(), nx)
        cross = A @ Pxt + Mt @ Ptt
        new[:nx, nx:] = cross
        new[nx:, :nx] = cross.T
        new[nx:, nx:] = Ptt
        new += m.Q
        self._set_P(new)
        self._x = m.fx(self._x, t)

    def update(self, y, t, mask):
        m = self.model
        H = m.H_jacobian(self._x, t)[mask]
        R = measurement_cov(m, t)[np.ix_(mask, mask)]
        Hs = sp.csr_matrix(H)                   # H = [D 0] with D sparse: O(nnz(H) n) products
        PHt = np.ascontiguousarray((Hs @ self._P).T)        # P H^T (P is exactly symmetric)
        S = np.asarray(Hs @ PHt) + R
        cho = sla.cho_factor(S, lower=True)
        K = sla.cho_solve(cho, PHt.T).T
        innov = y[mask] - m.hx(self._x, t)[mask]
        self._x = self._x + K @ innov
        self._set_P(joseph_update(self._P, K, PHt, S))
        self._observed(H, R, innov)
        return innov, S


# ---------------------------------------------------------------------- U-D factorised filter
def ud_factor(P, name: str = "P"):
    """U-D factorisation ``P = U diag(d) U^T`` of a symmetric positive semi-definite matrix.

    U is unit upper triangular, d >= 0 (Bierman 1977, section III.2). A pivot that is
    negative beyond round-off (relative to its diagonal entry) means P is indefinite: a
    ``ValueError`` naming ``name``; zero pivots (singular P) get a zero column in U.

    Returns
    -------
    U : (n, n) array
    d : (n,) array
    """
    P = as_float_array(name, P, shape=(None, None))
    n = P.shape[0]
    if P.shape != (n, n):
        raise ValueError(f"{name}: expected a square matrix, got shape {P.shape}")
    W = 0.5 * (P + P.T)
    diag0 = np.abs(np.diag(W)).copy()
    U = np.eye(n)
    d = np.zeros(n)
    for j in range(n - 1, -1, -1):
        dj = W[j, j]
        if dj < -64 * n * np.finfo(float).eps * max(diag0[j], 1e-300):
            raise ValueError(f"{name}: expected a positive semi-definite covariance, got one whose "
                             f"U-D factorisation has the negative pivot {dj:.3e} at index {j}")
        if dj <= 0.0:
            continue
        d[j] = dj
        u = W[:j, j] / dj
        U[:j, j] = u
        W[:j, :j] -= dj * np.outer(u, u)
    return U, d


def psd_factor(Q, name: str = "Q"):
    """``Q = G diag(q) G^T`` with q > 0, for a (possibly singular) PSD Q.

    A diagonal Q gives the columns of I with non-zero variance (exact); otherwise the
    eigen-decomposition, dropping eigenvalues below ``n eps max|lambda|``. Used by the MWGS
    time update, which accepts any such factor (it need not be triangular).
    """
    Q = as_float_array(name, Q, shape=(None, None))
    if np.count_nonzero(Q - np.diag(np.diag(Q))) == 0:
        q = np.diag(Q).copy()
        if np.any(q < 0):
            raise ValueError(f"{name}: expected non-negative variances, got minimum {q.min():.3e}")
        keep = q > 0
        return np.eye(len(q))[:, keep], q[keep]
    lam, V = np.linalg.eigh(0.5 * (Q + Q.T))
    tol = len(lam) * np.finfo(float).eps * max(np.abs(lam).max(), 1e-300)
    if lam.min() < -tol * 1e3:
        raise ValueError(f"{name}: expected a positive semi-definite matrix, got eigenvalue {lam.min():.3e}")
    keep = lam > tol
    return V[:, keep], lam[keep]


def mwgs(W, dw):
    """Thornton's modified weighted Gram-Schmidt: ``W diag(dw) W^T = U diag(d) U^T``.

    Parameters
    ----------
    W : (n, k) array, k >= n
        Rows to orthogonalise, e.g. ``[F U, G]`` for the time update
        ``P+ = F U D U^T F^T + G diag(q) G^T``.
    dw : (k,) array, >= 0
        Weights, e.g. ``[d, q]``.

    Returns
    -------
    U : (n, n) unit upper triangular array
    d : (n,) array, >= 0 by construction (weighted sums of squares)
    """
    W = np.array(W, float)
    dw = np.asarray(dw, float)
    n = W.shape[0]
    U = np.eye(n)
    d = np.zeros(n)
    for j in range(n - 1, -1, -1):
        wj = W[j]
        v = wj * dw
        dj = float(wj @ v)
        d[j] = dj
        if j == 0 or dj <= 0.0:
            continue
        u = (W[:j] @ v) / dj
        U[:j, j] = u
        W[:j] -= np.outer(u, wj)
    return U, d


def bierman_update(U, d, h, r):
    """Bierman's scalar measurement update of ``P = U diag(d) U^T`` in place.

    Parameters
    ----------
    U, d : the factors of the prior covariance (modified in place)
    h : (n,) array
        The measurement row.
    r : float, > 0
        Its noise variance.

    Returns
    -------
    gain : (n,) array
        Kalman gain ``P h / (h P h + r)`` for this measurement.
    s : float
        Innovation variance ``h P h + r``.

    Notes
    -----
    ``d_j <- d_j alpha_{j-1} / alpha_j`` with ``alpha_j = r + sum_{k<=j} d_k f_k^2 >= r > 0``:
    D stays non-negative by construction. Columns with ``f_j = 0`` are left untouched (exactly
    what the recursion does with them), which skips the unobserved part of the state.
    """
    f = U.T @ h
    v = d * f
    n = len(d)
    K = np.zeros(n)
    alpha = float(r)
    for j in np.flatnonzero(f):
        beta = alpha
        alpha = beta + v[j] * f[j]
        lam = -f[j] / beta
        d[j] *= beta / alpha
        col = U[:j, j].copy()
        U[:j, j] = col + lam * K[:j]
        K[:j] += v[j] * col
        K[j] = v[j]
    return K / alpha, alpha


class UDEngine(_Engine):
    """The U-D factorised filter (Bierman-Thornton), section 2.8 of the paper.

    ``P = U diag(d) U^T`` is never formed to be propagated: the time update is Thornton's MWGS
    of ``[F U, G]`` with weights ``[d, q]`` (``Q = G diag(q) G^T``, singular Q allowed: only
    its non-zero part enters), the measurement update Bierman's, one scalar measurement at a
    time. R is diagonal in :class:`sfem_filters.model.SFEMModel`, so its rows are processed as
    they are; a non-diagonal R is whitened by its Cholesky factor first (``L^-1 y``,
    ``L^-1 H``, unit variances). d >= 0 by construction, so P is positive semi-definite up to
    the round-off of forming it.
    """

    def __init__(self, model, ljung: bool = False):
        super().__init__(model, ljung)
        self._G, self._q = psd_factor(model.Q, "Q")
        R = np.asarray(model.R, float)
        self._R_diagonal = np.count_nonzero(R - np.diag(np.diag(R))) == 0
        self.reset(model.x0, model.P0)

    def reset(self, x, P):
        self._x = np.asarray(x, float).ravel().copy()
        self._U, self._d = ud_factor(P, "P")
        if self.ljung is not None:
            self.ljung.reset(np.asarray(P, float))

    @property
    def x(self):
        return self._x

    @property
    def P(self):
        P = (self._U * self._d) @ self._U.T
        return 0.5 * (P + P.T)

    @property
    def factors(self):
        """(U, d) with P = U diag(d) U^T (copies)."""
        return self._U.copy(), self._d.copy()

    def predict(self, t):
        F = self._jacobian(self._x, t)
        W = np.hstack([F @ self._U, self._G])
        self._U, self._d = mwgs(W, np.concatenate([self._d, self._q]))
        self._x = self.model.fx(self._x, t)

    def update(self, y, t, mask):
        m = self.model
        H = m.H_jacobian(self._x, t)[mask]
        R = measurement_cov(m, t)[np.ix_(mask, mask)]
        HU = H @ self._U
        S = (HU * self._d) @ HU.T + R
        innov = y[mask] - m.hx(self._x, t)[mask]
        if self._R_diagonal:
            Hw, ew, r = H, innov, np.diag(R)
        else:
            L = np.linalg.cholesky(R)
            Hw = sla.solve_triangular(L, H, lower=True)
            ew = sla.solve_triangular(L, innov, lower=True)
            r = np.ones(len(ew))
        x_prior = self._x
        x = x_prior.copy()
        for i in range(len(ew)):
            # residual of the linearised measurement at the current estimate: the sequence of
            # scalar updates equals the batch update with H taken at the prior
            res = ew[i] - Hw[i] @ (x - x_prior)
            gain, _ = bierman_update(self._U, self._d, Hw[i], r[i])
            x += gain * res
        self._x = x
        self._observed(H, R, innov)
        return innov, S


ENGINES = {"filterpy": FilterpyEngine, "structured": StructuredEngine, "ud": UDEngine}


@dataclass
class History:
    """Every step of a run, like filterpy's ``Saver``: one row per (loop, frame)."""

    loop: list = field(default_factory=list)
    frame: list = field(default_factory=list)
    x: list = field(default_factory=list)            # posterior state
    P_diag: list = field(default_factory=list)       # posterior variances
    innovation: list = field(default_factory=list)   # y - h(x_prior), NaN where unobserved
    S: list = field(default_factory=list)            # innovation covariance, NaN rows/cols unobserved
    nis: list = field(default_factory=list)          # normalised innovation squared
    n_obs: list = field(default_factory=list)        # number of observations in the update

    KEYS = ("loop", "frame", "x", "P_diag", "innovation", "S", "nis", "n_obs")

    def append(self, loop, frame, x, P, innovation, S, nis, n_obs):
        self.loop.append(loop)
        self.frame.append(frame)
        self.x.append(np.array(x, float))
        self.P_diag.append(np.diag(P).copy())
        self.innovation.append(innovation)
        self.S.append(S)
        self.nis.append(nis)
        self.n_obs.append(n_obs)

    def as_arrays(self) -> dict:
        return {k: np.asarray(getattr(self, k)) for k in self.KEYS}

    @classmethod
    def from_arrays(cls, arrays) -> "History":
        h = cls()
        for k in cls.KEYS:
            getattr(h, k).extend(list(np.asarray(arrays[k])))
        return h

    def loop_rows(self, loop: int | None = None) -> np.ndarray:
        """Row indices of one loop (default: the last)."""
        loops = np.asarray(self.loop)
        return np.flatnonzero(loops == (loops.max() if loop is None else loop))


def _check_observations(model, observations) -> np.ndarray:
    y = as_float_array("observations", observations, shape=(model.n_frames, model.dim_obs), finite=False)
    if np.any(np.isinf(y)):
        raise ValueError("observations: expected finite values or NaN for missing ones, got inf")
    return y


class FilterDivergence(RuntimeError):
    """The innovations stayed far outside their predicted spread for several frames in a row."""


def nearest_psd(P: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """Nearest symmetric positive semi-definite matrix in the Frobenius norm (Higham 1988).

    For the symmetric part B of P, Higham's ``(B + H) / 2`` with H the polar factor equals
    clipping B's negative eigenvalues at ``floor``.
    """
    P = as_float_array("P", P, shape=(None, None))
    if P.shape[0] != P.shape[1]:
        raise ValueError(f"P: expected a square matrix, got shape {P.shape}")
    B = 0.5 * (P + P.T)
    lam, V = np.linalg.eigh(B)
    return (V * np.maximum(lam, floor)) @ V.T


@dataclass
class Safeguards:
    """Run-time checks of a filter (section 2.8 of the paper and beyond).

    Parameters
    ----------
    covariance_repair : {"higham", "none"}
        After every step P must admit a Cholesky factor (positive definite to round-off). If it
        does not, ``"higham"`` replaces it by the nearest positive semi-definite matrix (plus
        ``jitter`` times its mean diagonal) and logs a warning; ``"none"`` raises.
    divergence_frames : int
        Frames in a row with NIS above the ``divergence_level`` quantile of chi2(m) that make
        the filter divergent: a warning, or :class:`FilterDivergence` with ``stop_on_divergence``.
    """

    covariance_repair: str = "higham"
    jitter: float = 1e-12
    divergence_level: float = 0.999
    divergence_frames: int = 4
    stop_on_divergence: bool = False
    repairs: list = field(default_factory=list)
    divergences: list = field(default_factory=list)

    def __post_init__(self):
        if self.covariance_repair not in ("higham", "none"):
            raise ValueError(f"covariance_repair: expected 'higham' or 'none', got {self.covariance_repair!r}")
        non_negative("jitter", self.jitter)
        probability("divergence_level", self.divergence_level)
        integer("divergence_frames", self.divergence_frames, 1)

    def check_covariance(self, engine, loop, t):
        if engine.cholesky() is not None:     # the structured engine keeps it for its next step
            return
        P = engine.P
        if self.covariance_repair == "none":
            raise FloatingPointError(f"P lost positive definiteness at loop {loop}, frame {t}")
        fixed = nearest_psd(P)
        fixed[np.diag_indices_from(fixed)] += self.jitter * max(np.mean(np.diag(fixed)), 1e-300)
        engine.reset(engine.x, fixed)
        self.repairs.append((loop, t))
        warnings.warn(f"covariance repaired (nearest PSD, Higham) at loop {loop}, frame {t}", RuntimeWarning)

    def check_nis(self, nis_run: list, loop, t, nis, m):
        from scipy import stats
        if m and nis > stats.chi2.ppf(self.divergence_level, m):
            nis_run.append(t)
        else:
            nis_run.clear()
        if len(nis_run) == self.divergence_frames:
            self.divergences.append((loop, t))
            msg = (f"filter inconsistent: NIS above its {self.divergence_level:.1%} chi-square bound for "
                   f"{self.divergence_frames} frames in a row (loop {loop}, frames {nis_run[0]}-{t})")
            if self.stop_on_divergence:
                raise FilterDivergence(msg)
            warnings.warn(msg, RuntimeWarning)


def filter_loop(engine, model, observations, loop: int = 0, history: History | None = None,
                safeguards: Safeguards | None = None):
    """One pass over the sequence: update at frame 0, then predict and update each frame.

    NaN observations are left out of their frame's update (rows of H, R and y); a frame with
    nothing observed is predict-only. With ``safeguards``, P is checked (and repaired) after
    every step and the NIS is monitored for divergence. Returns the posterior states, shape
    (n_frames, dim_state).
    """
    observations = _check_observations(model, observations)
    states = np.empty((model.n_frames, model.dim_state))
    nis_run: list = []
    for t in range(model.n_frames):
        if t > 0:
            engine.predict(t - 1)      # F P F^T + Q keeps a PSD P PSD: checked after the update
        y = observations[t]
        mask = ~np.isnan(y)
        innov = np.full(model.dim_obs, np.nan)
        S_full = np.full((model.dim_obs, model.dim_obs), np.nan)
        nis = np.nan
        if mask.any():
            e, S = engine.update(y, t, mask)
            innov[mask] = e
            S_full[np.ix_(mask, mask)] = S
            nis = float(e @ sla.cho_solve(sla.cho_factor(S), e))
        x = engine.x
        if not np.all(np.isfinite(x)) or not np.all(np.isfinite(engine.P)):
            raise FloatingPointError(f"the filter produced a non-finite state at loop {loop}, frame {t}")
        if safeguards is not None:
            safeguards.check_covariance(engine, loop, t)
            safeguards.check_nis(nis_run, loop, t, nis, int(mask.sum()))
        states[t] = x
        if history is not None:
            history.append(loop, t, x, engine.P, innov, S_full, nis, int(mask.sum()))
    return states


@dataclass
class CyclicResult:
    """Outcome of :func:`cyclic_estimate`."""

    states: np.ndarray          # filtered states of the last loop, (n_frames, dim_state)
    P_diag: np.ndarray          # their posterior variances
    theta: np.ndarray           # final material parameters
    P_theta: np.ndarray         # their covariance
    loops: int
    converged: bool
    rel_changes: list           # relative material change after each loop
    history: History


def _fingerprint(model, observations, engine: str, max_loops, tol, ljung: bool = False) -> str:
    """Hash of everything that determines a run: the model's own fingerprint when it has one
    (mechanics, loads, material, parameterisation, effects), the filter set-up and the data."""
    h = hashlib.sha256()
    if hasattr(model, "fingerprint"):
        h.update(model.fingerprint().encode())
    for a in (model.x0, model.P0, model.Q, model.R, np.nan_to_num(observations, nan=1e300),
              model.H_jacobian(model.x0, 0)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(f"{model.dim_state},{model.n_frames},{engine},{tol!r}".encode())
    if ljung:
        h.update(b"ljung")
    return h.hexdigest()


def _physical(model, theta):
    """E and nu of theta; the parameters themselves for a model without a material."""
    if not hasattr(model, "material_of_theta"):
        return np.asarray(theta, float)
    mat = model.material_of_theta(theta)
    return np.concatenate([mat.E, mat.nu])


def cyclic_estimate(model, observations, *, max_loops: int = 50, tol: float = 1e-3,
                    engine: str = "structured", progress: bool = False, checkpoint=None,
                    description: str = "cyclic loops", safeguards: Safeguards | None = None,
                    ljung: bool = False) -> CyclicResult:
    """Feed the periodic sequence again and again until the material converges (section 2.7).

    Each loop restarts the kinematic (and effect) states at ``model.x0`` with their initial
    covariance and no cross-covariance, and carries over the material estimate and its
    covariance block. The
    run stops when the relative change of (E, nu) over all elements (physical units) between
    loops is below ``tol`` or after ``max_loops`` loops. A model with a fixed material needs
    one loop. Each loop counts the cycle's information once more (exactly so for a linear
    model: ``P_k^-1 = P3(0)^-1 + k J``), so the steps shrink about like 1/k;
    :func:`sfem_filters.diagnostics.material_drift` compares each loop's step with the carried
    posterior sd.

    Parameters
    ----------
    observations : (n_frames, dim_obs) array
        Measurements in m; NaN marks a missing value.
    engine : {"structured", "filterpy", "ud"}
        Joseph-form covariance (``"structured"``, or filterpy's own EKF) or the U-D factorised
        Bierman-Thornton filter (``"ud"``).
    progress : bool
        Show a progress bar over loops.
    checkpoint : path, optional
        Saved (npz) after every loop; if it exists and matches this run, the run resumes
        from it and ends exactly as an uninterrupted run would.
    safeguards : Safeguards, optional
        Covariance checks and repair, divergence monitoring (default: ``Safeguards()``).
    ljung : bool
        Ljung's modification of the coupling term (Eq. 40, :class:`LjungCoupling`): needs a
        model that estimates at most :data:`LJUNG_MAX_PARAMS` parameters.
    """
    if engine not in ENGINES:
        raise ValueError(f"engine: expected one of {sorted(ENGINES)}, got {engine!r}")
    if int(max_loops) != max_loops or max_loops < 1:
        raise ValueError(f"max_loops: expected an integer >= 1, got {max_loops!r}")
    if not tol > 0:
        raise ValueError(f"tol: expected a positive relative tolerance, got {tol!r}")
    y = _check_observations(model, observations)
    safeguards = Safeguards() if safeguards is None else safeguards
    if not isinstance(ljung, (bool, np.bool_)):
        raise TypeError(f"ljung: expected True or False, got {ljung!r}")
    eng = ENGINES[engine](model, ljung=bool(ljung))
    nx = model.n_restart
    P0 = np.array(model.P0, float)
    theta = np.array(model.x0[nx:], float)
    P_theta = P0[nx:, nx:].copy()
    history = History()
    rel_changes: list = []
    start = 0
    fp = _fingerprint(model, y, engine, max_loops, tol, bool(ljung))
    if checkpoint is not None and os.path.exists(checkpoint):
        state = load_checkpoint(checkpoint, fp)
        theta, P_theta = state["theta"], state["P_theta"]
        rel_changes = list(state["rel_changes"])
        history = History.from_arrays(state)
        start = int(state["loops_done"])
    n_loops = 1 if not model.estimates_material else int(max_loops)
    converged = (bool(rel_changes) and rel_changes[-1] < tol) or (not model.estimates_material and start > 0)
    bar = None
    if progress:
        from tqdm import tqdm
        bar = tqdm(total=n_loops, initial=start, desc=description, unit="loop", leave=False)
    loops = start
    states = None
    try:
        for loop in range(start, n_loops):
            if converged:
                break
            x = np.array(model.x0, float)
            x[nx:] = theta
            P = P0.copy()
            P[nx:, nx:] = P_theta
            eng.reset(x, P)
            before = _physical(model, theta)
            states = filter_loop(eng, model, y, loop, history, safeguards)
            theta = eng.x[nx:].copy()
            P_theta = eng.P[nx:, nx:].copy()
            loops = loop + 1
            if model.estimates_material:
                after = _physical(model, theta)
                rel = float(np.linalg.norm(after - before) / np.linalg.norm(after))
                rel_changes.append(rel)
                converged = rel < tol
            else:
                converged = True
            if checkpoint is not None:
                save_checkpoint(checkpoint, fp, theta, P_theta, rel_changes, history, loops)
            if bar is not None:
                bar.update(1)
                if rel_changes:
                    bar.set_postfix(rel_change=f"{rel_changes[-1]:.2e}")
    finally:
        if bar is not None:
            bar.close()
    if states is None:  # resumed from a finished run: recover the last loop from the history
        arrays = history.as_arrays()
        last = arrays["loop"] == arrays["loop"].max()
        states = arrays["x"][last]
    if model.estimates_material and not converged:
        warnings.warn(f"cyclic_estimate: the material did not converge in {loops} loops "
                      f"(last relative change {rel_changes[-1]:.2e} > tol {tol:g})", RuntimeWarning)
    arrays = history.as_arrays()
    last = arrays["loop"] == arrays["loop"].max()
    return CyclicResult(states=states, P_diag=arrays["P_diag"][last], theta=theta, P_theta=P_theta,
                        loops=loops, converged=converged, rel_changes=rel_changes, history=history)


def save_checkpoint(path, fingerprint, theta, P_theta, rel_changes, history, loops_done):
    """Write a resumable checkpoint atomically (npz)."""
    tmp = f"{path}.tmp.npz"
    np.savez(tmp, format_version=CHECKPOINT_FORMAT, fingerprint=fingerprint, theta=theta,
             P_theta=P_theta, rel_changes=np.asarray(rel_changes, float), loops_done=loops_done,
             **history.as_arrays())
    os.replace(tmp, path)


def load_checkpoint(path, fingerprint=None) -> dict:
    """Read a checkpoint; a truncated or foreign file raises ``ValueError``."""
    try:
        with np.load(path, allow_pickle=False) as f:
            data = {k: f[k] for k in f.files}
    except Exception as exc:  # zipfile / format errors differ between numpy versions
        raise ValueError(f"checkpoint: {path} is not a readable checkpoint ({exc})") from None
    need = {"format_version", "fingerprint", "theta", "P_theta", "rel_changes", "loops_done",
            *History.KEYS}
    missing = need - set(data)
    if missing:
        raise ValueError(f"checkpoint: {path} lacks {sorted(missing)}")
    if int(data["format_version"]) != CHECKPOINT_FORMAT:
        raise ValueError(f"checkpoint: {path} has format {int(data['format_version'])}, "
                         f"expected {CHECKPOINT_FORMAT}")
    if fingerprint is not None and str(data["fingerprint"]) != fingerprint:
        raise ValueError(f"checkpoint: {path} belongs to a different model or data set")
    return data


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
        return self._n_frames

    @property
    def estimates_material(self) -> bool:
        return self.dim_theta > 0

    def theta_of(self, z) -> np.ndarray:
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

