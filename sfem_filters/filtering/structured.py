"""The structured engine: F = [[A, M_t], [0, I]] block by block, Cholesky factors, Joseph form."""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.linalg.blas as blas
import scipy.sparse as sp

from .base import DenseEngine
from .protocol import measurement_cov

__all__ = ["StructuredEngine", "joseph_update", "propagate_factored"]


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


def propagate_factored(A, Mt, P, L, nx: int) -> np.ndarray:
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


class StructuredEngine(DenseEngine):
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
        super().reset(x, P)
        if self.ljung is not None:
            self.ljung.reset(self._P)

    def predict(self, t):
        m = self.model
        nx = m.n_restart        # F = [[A', M'], [0, I]] with A' over kinematics and effect states
        F = self._jacobian(self._x, t)
        A, Mt = F[:nx, :nx], F[:nx, nx:]
        P = self._P
        Pxt, Ptt = P[:nx, nx:], P[nx:, nx:]
        new = np.empty_like(P)
        new[:nx, :nx] = propagate_factored(A, Mt, P, self.cholesky(), nx)
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
