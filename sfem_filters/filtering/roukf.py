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

Where that leaves out most of the model's uncertainty (a model whose frame-to-frame kinematics are
mostly process noise, such as the measured slice's penalty drive, whose spring targets move by
about the landmarks' step each frame), the predicted innovation covariance ``HL HL^T + W`` is
far too small, the innovations are many times their predicted spread (the NIS / dof of
``docs/_generated/peers_measured.md``), and the gain hands the misfit to the parameters: the
estimate itself (not the spread of its sigma points) runs off, until the model rejects a sigma
point (a stiffness field too wide to be positive definite in double precision). The EKF with its
Q set to zero does the same, so this is the method's limit, not a defect of the sigma points or
of the parameters' transform (``tests/filtering/test_roukf.py``). The engine then raises a
``ValueError`` that says so, with the model's own error as its cause, and names the setting to
change: a filter that keeps the process noise (engine ``"structured"``: ``estimator="cyclic"``
or ``"smoother"``). The restart states the parameters do not move (an effect amplitude with its
own random walk) stay at their initial value in this filter.

Drivers: it is a filter, so it runs in the cyclic driver (``cyclic_estimate(model, y,
engine="roukf")``, ``CyclicEKF(engine="roukf")``: loops, checkpoints, safeguards, progress bar
and the one-cycle covariance as for the EKF), and so in ``sfem-filters dense --estimator roukf``.
Not in the iterated smoother: its Gauss-Newton steps are built on the tangent operator (the
linearised transition and M_t) that this filter exists to avoid.
"""
from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from scipy import stats

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


def _cholesky_with_jitter(P, tries: int = 6) -> np.ndarray:
    """Cholesky factor of a symmetric P, adding ``10^k * 1e-14 * mean(diag P)`` to its diagonal
    (k = 0, 1, ...) when round-off has left it semi-definite: after many updates the rank-p
    factor can carry singular values below the double-precision floor of its largest ones."""
    scale = max(float(np.mean(np.diag(P))), 1e-300)
    for k in range(tries + 1):
        try:
            return np.linalg.cholesky(P if k == 0 else P + (10.0 ** (k - 1) * 1e-14 * scale) * np.eye(len(P)))
        except np.linalg.LinAlgError:
            continue
    raise ValueError("P: the parameter block must be positive definite for the reduced-order UKF "
                     f"(still not with a jitter of {10.0 ** (tries - 1) * 1e-14:g} of its mean variance)")


class ROUKFEngine(Engine):
    """The reduced-order UKF (module docstring) as an engine of the cyclic driver.

    The factor is stored normalised, ``U = I`` after every step (``L <- L R^-1`` with
    ``U = R^T R``), which avoids inverting ``U``; ``P = L L^T`` is formed on demand (rank p, so
    not positive definite): the safeguards' check asks :meth:`cholesky`, which answers for the
    factor.
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
        self._worst = None              # (NIS / dof, frame) of this loop's most inconsistent update, above 99.9 %

    def reset(self, x, P) -> None:
        x = np.asarray(x, float).ravel()
        P = np.asarray(P, float)
        nx = self.nx
        Ptt = 0.5 * (P[nx:, nx:] + P[nx:, nx:].T)
        C = _cholesky_with_jitter(Ptt)
        self._z = x.copy()
        self._L = np.vstack([np.linalg.solve(Ptt, P[nx:, :nx]).T, np.eye(self.p)]) @ C
        self._start, self._start_sd = x[nx:].copy(), np.sqrt(np.diag(Ptt))
        self._worst = None

    @property
    def x(self) -> np.ndarray:
        return self._z

    @property
    def P(self) -> np.ndarray:
        return self._L @ self._L.T

    def cholesky(self):
        """The square root ``S = L U^-1/2`` (n, p), ``P = S S^T``, while it is finite and of full
        rank p (the reduced covariance is positive definite on its subspace); else None."""
        S = self._L
        if not np.all(np.isfinite(S)) or np.linalg.matrix_rank(S[self.nx:]) < self.p:
            return None
        return S

    def _through(self, f, Z, t: int, step: str) -> np.ndarray:
        """``f(z_i, t)`` of every sigma point (columns of Z), as columns. A model error
        (``ValueError``, ``FloatingPointError``, ``LinAlgError``) after an update of this loop
        whose innovations were beyond the 99.9 % chi-square bound is the filter's divergence:
        re-raised as a ``ValueError`` naming the cause (:func:`_divergence_message`), the model's
        error as its cause; any other is passed on unchanged."""
        out = []
        for i in range(Z.shape[1]):
            try:
                out.append(np.asarray(f(Z[:, i], t), float).ravel())
            except (ValueError, FloatingPointError, np.linalg.LinAlgError) as err:
                if self._worst is None:
                    raise
                theta, sd = self._z[self.nx:], self._start_sd
                moved = np.abs(theta - self._start)
                spread = float(np.max(np.abs(Z[self.nx:] - theta[:, None]) / sd[:, None]))
                has_q = bool(np.any(np.asarray(self.model.Q, float)[:self.nx, :self.nx]))
                raise ValueError(_divergence_message(step, self._worst, float(np.max(moved / sd)), float(moved.max()),
                                                     spread, i, has_q, err)) from err
        return np.column_stack(out)

    def predict(self, t: int) -> None:
        Z = self._z[:, None] + self._L @ self.I
        Zf = self._through(self.model.fx, Z, t, f"frame {t} to {t + 1}")
        self._z = Zf.mean(axis=1)
        self._L = self.alpha * Zf @ self.I.T            # U^- = I: L^- is a square root of P^-

    def update(self, y, t: int, mask) -> tuple:
        L = self._L                                     # sampled square root (U = I)
        Z = self._z[:, None] + L @ self.I
        Y = self._through(self.model.hx, Z, t, f"observing frame {t}")[mask]
        W = measurement_cov(self.model, t)[np.ix_(mask, mask)]
        HL = self.alpha * Y @ self.I.T
        e = np.asarray(y, float)[mask] - Y.mean(axis=1)
        cW = sla.cho_factor(W)
        WiHL = sla.cho_solve(cW, HL)
        U = np.eye(self.p) + HL.T @ WiHL                # U^+ = I + HL^T W^-1 HL
        R = sla.cholesky(0.5 * (U + U.T))               # U^+ = R^T R, R upper
        # z^+ = z + L U^-1 HL^T W^-1 e; the new square root L R^-1 keeps U = I (P = L U^-1 L^T)
        self._z = self._z + L @ sla.cho_solve((R, False), WiHL.T @ e)
        self._L = sla.solve_triangular(R, L.T, trans="T", lower=False).T
        S = HL @ HL.T + W
        S = 0.5 * (S + S.T)
        m = int(e.size)
        nis = float(e @ sla.cho_solve(sla.cho_factor(S), e))
        if nis > stats.chi2.ppf(0.999, m) and (self._worst is None or nis / m > self._worst[0]):
            self._worst = (nis / m, t)
        return e, S


def _divergence_message(step: str, worst: tuple, moved_sd: float, moved: float, spread: float, point: int,
                        has_q: bool, err: Exception) -> str:
    """The reduced-order UKF's divergence, explained: where the model rejected a sigma point, the
    innovations' excess (``worst``: NIS / dof and frame), how far the estimate moved from the
    loop's start (in its sd there, ``moved_sd``, and in parameter units) against its sigma
    points' spread (``spread``, in the same sd), what the filter leaves out (``has_q``: the model
    has process noise on its restart states) and the setting to change."""
    left_out = "the model's process noise Q" if has_q else "the model's misfit"
    return (f"reduced-order UKF diverged ({step}): without process noise its parameters absorbed the misfit; "
            f"use estimator 'cyclic' or 'smoother' (engine 'structured'). NIS/dof up to {worst[0]:.3g} (frame "
            f"{worst[1]}); the estimate itself ran off, {moved_sd:.3g} sd (up to {moved:.3g}) from the loop's start, "
            f"its sigma points within {spread:.3g} sd of it: the covariance of rank p has no room for {left_out}, "
            f"so the innovations are explained by the parameters (Moireau & Chapelle 2011). The model rejected "
            f"sigma point {point}: {err}")
