"""The engine interface shared by every filter implementation."""
from __future__ import annotations

import numpy as np

from .ljung import LjungCoupling

__all__ = ["Engine", "DenseEngine"]


class Engine:
    """The engine interface, declared once: every engine runs the same filter on a model.

    An engine holds the current state estimate and its covariance and moves them one frame at
    a time, as filterpy's filters do; :func:`sfem_filters.filtering.cyclic.filter_loop` drives
    it over a sequence. Subclasses implement :meth:`reset`, :meth:`predict`, :meth:`update`
    and the properties :attr:`x` and :attr:`P`; :meth:`cholesky` has a default.

    Parameters
    ----------
    model : :class:`sfem_filters.filtering.protocol.FilterModel`
    ljung : bool
        Add Ljung's gain-derivative term to the parameter columns of F (Eq. 40,
        :class:`sfem_filters.filtering.ljung.LjungCoupling`).
    """

    #: Whether the engine has the tangent operator Ljung's term needs (the unscented ones do not).
    supports_ljung = True

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

    def reset(self, x, P) -> None:
        """Set the estimate to state ``x`` (n,) and covariance ``P`` (n, n)."""
        raise NotImplementedError

    @property
    def x(self) -> np.ndarray:
        """Current state estimate, (n,)."""
        raise NotImplementedError

    @property
    def P(self) -> np.ndarray:
        """Current covariance, (n, n), symmetric."""
        raise NotImplementedError

    def predict(self, t: int) -> None:
        """Time update from frame ``t`` to ``t + 1``: ``x <- fx(x, t)``, ``P <- F P F^T + Q``."""
        raise NotImplementedError

    def update(self, y, t: int, mask) -> tuple:
        """Measurement update of frame ``t`` with the rows ``mask`` (bool, m) of ``y`` (m,).

        Returns the innovation ``y - h(x_prior)`` of those rows and its covariance ``S``.
        """
        raise NotImplementedError

    def cholesky(self):
        """Lower Cholesky factor of the current P, or None if P is not positive definite."""
        try:
            return np.linalg.cholesky(0.5 * (self.P + self.P.T))
        except np.linalg.LinAlgError:
            return None


class DenseEngine(Engine):
    """An engine that keeps ``x`` and a dense, exactly symmetric ``P``, with its Cholesky factor
    computed once on demand and cached until P changes (:meth:`_set_P`)."""

    def reset(self, x, P) -> None:
        self._x = np.asarray(x, float).ravel().copy()
        P = np.asarray(P, float)
        self._set_P(0.5 * (P + P.T))       # the steps keep it exactly symmetric from here on

    def _set_P(self, P) -> None:
        self._P = P
        self._L = None                     # Cholesky factor of P, computed on demand

    @property
    def x(self) -> np.ndarray:
        return self._x

    @property
    def P(self) -> np.ndarray:
        return self._P

    def cholesky(self):
        """Lower Cholesky factor of the current P (cached), or None if P is not positive definite."""
        if self._L is None:
            try:
                self._L = np.linalg.cholesky(self._P)
            except np.linalg.LinAlgError:
                self._L = False
        return None if self._L is False else self._L
