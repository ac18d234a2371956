"""The U-D factorised (Bierman-Thornton) filter, section 2.8 of the paper.

P = U diag(d) U^T with U unit upper triangular and d >= 0 by construction: Thornton's
modified weighted Gram-Schmidt time update and Bierman's scalar measurement update.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla

from .._validate import as_float_array
from .base import Engine
from .protocol import measurement_cov

__all__ = ["UDEngine", "ud_factor", "psd_factor", "mwgs", "bierman_update"]


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


class UDEngine(Engine):
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
