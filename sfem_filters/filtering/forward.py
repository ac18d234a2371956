"""The forward half of the smoother: the Kalman filter of a linearised model, and what it keeps.

:func:`kalman_forward` runs the Kalman filter of a
:class:`~sfem_filters.filtering.linearised.LinearisedModel` over the frames with the structured
engine's algebra (F = [[A, M_t], [0, I]] block by block with a sparse A, Cholesky factors of S,
the Joseph update; :class:`LinearisedEngine`), and keeps for the backward pass of
:func:`sfem_filters.filtering.smoother.smooth_backward` what ``store`` asks (:data:`STORE`): the
prior covariance of every frame (or of every k-th, checkpoints), or the gains and innovations
alone. Its result, :class:`ForwardPass`, also carries the innovations, their covariances, the NIS
and the log-likelihood of the linearised model (prediction-error decomposition).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from .._validate import integer
from .base import DenseEngine
from .linearised import LinearisedModel
from .structured import joseph_update

__all__ = ["STORE", "LinearisedEngine", "ForwardPass", "kalman_forward"]

LOG_2PI = float(np.log(2.0 * np.pi))


#: What a forward pass keeps for the backward pass (:func:`kalman_forward`'s ``store``).
STORE = ("covariance", "mean", "none")


def _store_mode(store) -> str:
    """``store`` as one of :data:`STORE` (``True``: ``"covariance"``, ``False``: ``"none"``)."""
    if isinstance(store, (bool, np.bool_)):
        return "covariance" if store else "none"
    if store not in STORE:
        raise ValueError(f"store: expected one of {STORE} (or True / False), got {store!r}")
    return store


class LinearisedEngine(DenseEngine):
    """The Kalman filter of a :class:`LinearisedModel` in its coordinates ``[xi; theta]``.

    Records, per frame, what the backward pass needs. ``store="covariance"`` (or ``True``): the
    prior mean and covariance, and the observed rows, innovation, Cholesky factor of S and gain of
    the update (n^2 floats a frame, what smoothed covariances need); with ``every`` k > 1 the
    prior mean and covariance of every k-th frame only (checkpoints, from which the backward pass
    recomputes the frames between: :func:`~sfem_filters.filtering.smoother.smooth_backward`).
    ``"mean"``: the update's rows, innovation, factor and gain only, and the initial mean and
    covariance (n m floats a frame, what smoothed means need). ``"none"`` (``False``): nothing.
    """

    def __init__(self, lin: LinearisedModel, theta_mean, theta_cov, store=True, every: int = 1):
        self.lin, self.ljung, self.store = lin, None, _store_mode(store)
        self.every = integer("every", every, 1)
        self.nr, self.p = lin.n_restart, lin.n_params
        self.priors: dict = {}          # frame -> (prior mean, prior covariance)
        # frame -> what a safeguard's repair there changed: (mean, covariance) after it for the
        # checkpoints' replay, its change of the covariance for the means' forward recursion
        self.repaired: dict = {}
        self.observations = None        # what the backward pass replays between checkpoints
        self.updates: dict = {}
        self.log_likelihood = 0.0
        x0 = np.concatenate([lin.xi0, np.asarray(theta_mean, float)])
        P0 = sla.block_diag(lin.P0, np.asarray(theta_cov, float))
        self.reset(x0, P0)
        self.initial = (self._x.copy(), self._P.copy()) if self.store == "mean" else None
        if self.store == "covariance":
            self.priors[0] = (self._x.copy(), self._P.copy())

    def predict(self, t):
        lin, nr = self.lin, self.nr
        A, M = lin.A_at(t), lin.M[t]
        P = self._P
        Prr, Prt, Ptt = P[:nr, :nr], P[:nr, nr:], P[nr:, nr:]
        AP = np.asarray(A @ Prr)
        APA = np.asarray(A @ AP.T)
        new = np.empty_like(P)
        rr = 0.5 * (APA + APA.T)
        if self.p:
            APrt = np.asarray(A @ Prt)
            MPtt = M @ Ptt
            Z = (APrt + 0.5 * MPtt) @ M.T
            rr += Z + Z.T
            cross = APrt + MPtt
            new[:nr, nr:] = cross
            new[nr:, :nr] = cross.T
            new[nr:, nr:] = Ptt
        new[:nr, :nr] = rr + lin.Q_at(t)
        x = self._x
        xr = np.asarray(A @ x[:nr]).ravel() + lin.c[t]
        if self.p:
            xr += M @ (x[nr:] - lin.theta_bar)
        self._x = np.concatenate([xr, x[nr:]])
        self._set_P(new)
        if self.store == "covariance" and (t + 1) % self.every == 0:
            self.priors[t + 1] = (self._x.copy(), self._P.copy())

    def update(self, y, t, mask):
        lin, nr = self.lin, self.nr
        H = lin.H[mask]
        R = lin.R[t][np.ix_(mask, mask)]
        PHt = self._P[:, :nr] @ H.T
        S = H @ PHt[:nr] + R
        cho = sla.cho_factor(S, lower=True)
        K = sla.cho_solve(cho, PHt.T).T
        e = y[mask] - H @ self._x[:nr]
        self._x = self._x + K @ e
        self._set_P(joseph_update(self._P, K, PHt, S))
        quad = float(e @ sla.cho_solve(cho, e))
        logdet = 2.0 * float(np.sum(np.log(np.diag(cho[0]))))
        self.log_likelihood -= 0.5 * (quad + logdet + len(e) * LOG_2PI)
        self.updates[t] = (mask, e, cho, K, quad) if self.store != "none" else (mask, None, None, None, quad)
        return e, S


@dataclass(eq=False)
class ForwardPass:
    """The Kalman filter's run over the frames (coordinates of the linearised model: ``[xi; theta]``)."""

    engine: LinearisedEngine       # with the priors, gains and factors the backward pass needs
    filtered: np.ndarray           # (n_frames, n) filtered means
    innovation: np.ndarray         # (n_frames, m), NaN where not observed
    S: np.ndarray                  # (n_frames, m, m), NaN rows/cols where not observed
    nis: np.ndarray                # (n_frames,), NaN where nothing observed
    n_obs: np.ndarray              # (n_frames,)

    @property
    def log_likelihood(self) -> float:
        """log p(y) of the linearised model (prediction-error decomposition)."""
        return self.engine.log_likelihood

    @property
    def fit(self) -> float:
        """``1/2 sum_t e_t^T S_t^-1 e_t``: for a linear-Gaussian model the minimum over the
        trajectory of the negative log joint density without its constant terms (completing the
        square), i.e. the profile MAP cost less the parameters' prior term."""
        return 0.5 * float(np.nansum(self.nis))



def kalman_forward(lin: LinearisedModel, observations, theta_mean=None, theta_cov=None, *, safeguards=None,
                   check_every_frame: bool = True, monitor_nis: bool = False, label: int = 0,
                   store=True, every: int = 1) -> ForwardPass:
    """The forward (filter) half of :func:`~sfem_filters.filtering.smoother.smooth`.

    ``safeguards`` checks (and repairs) P after every frame when ``check_every_frame``, else only
    after the last one (a Cholesky factor costs n^3/3, more than the rest of a frame's work here);
    finiteness and positive variances are checked every frame either way. ``monitor_nis`` also
    watches the NIS for divergence. ``store`` (:data:`STORE`): what is kept for a backward pass,
    ``"covariance"`` (``True``, the default) the prior covariance of every frame, n^2 floats a
    frame, for smoothed covariances; ``"mean"`` the gains and innovations only, n m floats a frame,
    for smoothed means; ``"none"`` (``False``) nothing (the filter's own results only). ``every``
    (with ``"covariance"``): keep the prior covariance of every ``every``-th frame only, and let
    the backward pass recompute the others from them, a segment at a time (checkpointing:
    ``(frames / every + every) n^2`` floats instead of ``frames n^2``, for one forward pass more;
    :func:`~sfem_filters.filtering.memory.covariance_interval`).
    """
    y = np.asarray(observations, float)
    eng = LinearisedEngine(lin, lin.theta0 if theta_mean is None else theta_mean,
                           lin.P_theta0 if theta_cov is None else theta_cov, store=store, every=every)
    if eng.store == "covariance" and eng.every > 1:
        eng.observations = y
    T, m = lin.n_frames, lin.dim_obs
    filtered = np.empty((T, lin.dim_state))
    innov = np.full((T, m), np.nan)
    S_all = np.full((T, m, m), np.nan)
    nis = np.full(T, np.nan)
    n_obs = np.zeros(T, int)
    run: list = []
    for t in range(T):
        if t > 0:
            eng.predict(t - 1)
        mask = ~np.isnan(y[t])
        if mask.any():
            e, S = eng.update(y[t], t, mask)
            innov[t, mask] = e
            S_all[t][np.ix_(mask, mask)] = S
            nis[t] = eng.updates[t][4]
            n_obs[t] = int(mask.sum())
        if not np.all(np.isfinite(eng.x)) or not np.all(np.isfinite(eng.P)) or np.any(np.diag(eng.P) <= 0):
            raise FloatingPointError(f"the smoother's forward pass lost its covariance (non-finite or a variance "
                                     f"<= 0) at pass {label}, frame {t}")
        if safeguards is not None and (check_every_frame or t == T - 1):
            before = eng.P
            safeguards.check_covariance(eng, label, t)
            if eng.P is not before:                                # repaired: what the backward pass must know
                if eng.store == "mean":
                    eng.repaired[t] = eng.P - before
                elif eng.observations is not None:
                    eng.repaired[t] = (eng.x.copy(), eng.P.copy())  # the replay between checkpoints resumes here
        if safeguards is not None and monitor_nis:
            safeguards.check_nis(run, label, t, nis[t], n_obs[t])
        filtered[t] = eng.x
    return ForwardPass(engine=eng, filtered=filtered, innovation=innov, S=S_all, nis=nis, n_obs=n_obs)

