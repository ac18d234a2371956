"""The fixed-interval (Rauch-Tung-Striebel) smoother of a linearised model, one pass of the cycle.

:func:`smooth` runs the Kalman filter of a
:class:`~sfem_filters.filtering.linearised.LinearisedModel` forward over the frames (the
structured engine's algebra: F = [[A, M_t], [0, I]] block by block with a sparse A, Cholesky
factors of S, the Joseph update) and then the backward pass in Bierman's modified
Bryson-Frazier form (Bierman 1977, ch. X): with the filter's prior ``x_t-``, ``P_t-``, gain
``K_t``, innovation ``e_t`` and covariance ``S_t``, from ``lambda = 0``, ``Lambda = 0`` after
the last frame,

    lambda~_t = (I - K_t H)^T lambda_t - H^T S_t^-1 e_t
    Lambda~_t = (I - K_t H)^T Lambda_t (I - K_t H) + H^T S_t^-1 H
    x_t|T = x_t- - P_t- lambda~_t,          P_t|T = P_t- - P_t- Lambda~_t P_t-
    lambda_{t-1} = F_{t-1}^T lambda~_t,     Lambda_{t-1} = F_{t-1}^T Lambda~_t F_{t-1}.

These are the RTS smoother's estimates exactly (:func:`rts_reference` computes them with the
textbook gains ``G_t = P_t|t F_t^T P_t+1|t^-1`` by Cholesky solves; the tests compare the two)
without any solve with an n x n matrix: smoothed means cost O(n^2) a frame, and covariances are
formed only for the outputs asked for. ``Lambda~_t`` is a sum over the frames after t of
observed rows carried back, so its rank is at most the number of rows observed from t on: while
that is below n it is kept as a factor ``W W^T`` (n x r; the update appends ``H^T L_t^-T``,
``S_t = L_t L_t^T``, to ``(I - K_t H)^T W``), which makes the covariance of c output columns
O(c n r) instead of O(c n^2) (:data:`FACTOR_RANK`). Static parameters are part of the state, so
the smoothed ``theta`` and its covariance are those of the whole cycle.

Memory: smoothed means need only the gains and innovations (n m floats a frame,
``store="mean"``: the disturbance smoother, :func:`smooth_backward`), and that is what
:func:`smooth` keeps when no covariance is asked for, as in every pass of the iterated smoother
but its last. Smoothed covariances need the prior covariance of every frame (n^2 floats a
frame); where those do not fit the memory, only every k-th is kept and the backward pass
recomputes the frames between, a segment at a time (checkpointing, :func:`covariance_interval`),
with the same numbers.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .._validate import integer
from ..resources import available_memory
from .base import DenseEngine
from .linearised import LinearisedModel
from .structured import joseph_update

__all__ = ["STORE", "LinearisedEngine", "ForwardPass", "SmoothedPass", "kalman_forward", "smooth_backward", "smooth",
           "rts_reference", "available_memory", "check_memory", "covariance_interval", "stored_bytes", "WORKING",
           "InsufficientMemory", "MEMORY_ADVICE"]

LOG_2PI = float(np.log(2.0 * np.pi))


#: The covariance backward pass keeps ``Lambda`` as a factor ``W W^T`` (n x r) while its rank r,
#: the rows observed after the frame, stays below this share of n; then the dense n x n recursion.
#: With r < n the factor's products (O(c n r) per block of c output columns) are the cheaper.
FACTOR_RANK = 1.0

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
    recomputes the frames between: :func:`smooth_backward`). ``"mean"``: the update's rows,
    innovation, factor and gain only, and the initial mean and covariance (n m floats a frame,
    what smoothed means need). ``"none"`` (``False``): nothing.
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
        new[:nr, :nr] = rr + lin.Q
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


@dataclass(eq=False)
class SmoothedPass:
    """Outcome of :func:`smooth` (coordinates of the linearised model: ``[xi; theta]``)."""

    forward: ForwardPass
    smoothed: np.ndarray           # (n_frames, n) smoothed means
    theta: np.ndarray              # smoothed (whole-cycle) parameters
    P_theta: np.ndarray            # their covariance
    variances: dict = field(default_factory=dict)   # name -> (n_frames, k) smoothed output variances

    def __getattr__(self, name):   # innovation, S, nis, n_obs, log_likelihood, filtered, fit
        if name == "forward":
            raise AttributeError(name)
        return getattr(self.forward, name)


#: Head-room of a smoothing run over what :func:`check_memory` counts (the stored prior
#: covariances and :data:`WORKING` n x n matrices): the model's dense operators, the interpreter
#: and its libraries come on top (the resident peaks of the whole runs on the docs' validation pages are 1.8-2.3 times
#: what their last, covariance pass keeps).
PEAK_FACTOR = 3.0


#: What to do when a smoothing run does not fit the memory.
MEMORY_ADVICE = ("reduce the state (fewer nodes, for example every other pixel of the tissue; fewer material "
                 "parameters) or the frames, or run where more memory is free")


class InsufficientMemory(MemoryError):
    """:func:`check_memory`'s refusal of a run whose stored covariances cannot fit (its message
    gives the sizes and :data:`MEMORY_ADVICE`)."""


#: n x n matrices a pass holds besides the stored ones: the filter's covariance and its next, the
#: backward pass's information matrix, and the temporaries of a step.
WORKING = 6


def stored_bytes(n: int, frames: int, every: int = 1, observed: int = 0) -> float:
    """Bytes a pass keeps for its backward pass (8-byte floats).

    Parameters
    ----------
    n : int
        State dimension.
    frames : int
        Frames of the pass (:func:`kalman_forward` keeps one prior covariance per frame).
    every : int or None
        A covariance pass keeping the prior covariance of one frame in ``every`` and recomputing
        up to ``every - 1`` more at a time in the backward pass (:func:`smooth_backward`); None:
        a pass for means, which keeps no covariance.
    observed : int
        Observed rows over all frames (the gains kept, n floats each, by either kind of pass).

    Returns
    -------
    float
        Bytes; a safeguard's repair between checkpoints keeps one n x n matrix more (rare, not
        counted).
    """
    gains = 8.0 * float(observed) * n
    if every is None or frames <= 0:
        return gains
    return gains + 8.0 * float(n) ** 2 * (-(-frames // every) + min(every, frames) - 1)


def covariance_interval(n: int, frames: int, available: float | None = None, observed: int = 0) -> int:
    """Frames between the prior covariances a covariance pass keeps (:func:`smooth`'s ``every``).

    1 (every frame, no recomputation) where :data:`PEAK_FACTOR` times what that pass holds
    (:func:`stored_bytes` and :data:`WORKING` n x n matrices) fits the available memory, or
    where the system does not say; otherwise ``ceil(sqrt(frames))``, which keeps about
    ``2 sqrt(frames) n^2`` floats instead of ``frames n^2`` (checkpointing, Griewank & Walther
    2008, ch. 12) for one forward pass more, with the same numbers.

    Parameters
    ----------
    n, frames, observed :
        As for :func:`stored_bytes`.
    available : float, optional
        Bytes available (default :func:`~sfem_filters.resources.available_memory`).

    Returns
    -------
    int, >= 1
    """
    available = available_memory() if available is None else float(available)
    working = 8.0 * WORKING * float(n) ** 2
    if available is None or frames <= 1 or PEAK_FACTOR * (stored_bytes(n, frames, 1, observed) + working) <= available:
        return 1
    return math.isqrt(frames - 1) + 1


def _size(nbytes: float) -> str:
    """Bytes as GB, or MB below one GB."""
    return f"{nbytes * 1e-9:.1f} GB" if nbytes >= 1e9 else f"{nbytes * 1e-6:.0f} MB"


def check_memory(n: int, frames: int, available: float | None = None, covariance: bool = True,
                 observed: int = 0) -> None:
    """Refuse a run whose passes cannot fit the memory, warn where the run's peak may not.

    Every pass holds :data:`WORKING` n x n matrices and the gains of the observed rows; a
    covariance pass also keeps the prior covariances its backward pass needs, every frame's or,
    where those do not fit, checkpoints (:func:`covariance_interval`, :func:`stored_bytes`).
    More than the available memory is a :class:`MemoryError` that says how much and what to
    reduce, instead of the operating system killing the process midway; more than a
    :data:`PEAK_FACTOR` share of it is a ``RuntimeWarning``.

    Parameters
    ----------
    n : int
        State dimension (kinematics, effect states and parameters).
    frames : int
        Frames of the pass.
    available : float, optional
        Bytes available (default :func:`~sfem_filters.resources.available_memory`; nothing is checked where unknown).
    covariance : bool
        Whether the run makes a covariance pass (smoothed variances of the kinematics).
    observed : int
        Observed rows over all frames (non-missing values of the observations).
    """
    available = available_memory() if available is None else float(available)
    if available is None:
        return
    working = 8.0 * WORKING * float(n) ** 2
    if covariance:
        every = covariance_interval(n, frames, available, observed)
        stored = stored_bytes(n, frames, every, observed)
        kept = (f"a {n} x {n} covariance for each of {frames} frames" if every == 1 else
                f"a {n} x {n} covariance for one frame in {every} of {frames}, recomputing the others")
    else:
        stored, kept = stored_bytes(n, frames, None, observed), "no covariance of any frame (means only)"
    need = stored + working
    what = (f"the smoother keeps {kept} and gains ({_size(stored)}) and works in {WORKING} {n} x {n} matrices "
            f"({_size(working)}; about {_size(PEAK_FACTOR * need)} at the run's peak)")
    if need > available:
        raise InsufficientMemory(f"model: {what}, more than the {_size(available)} available; {MEMORY_ADVICE}")
    if PEAK_FACTOR * need > available:
        warnings.warn(f"{what}, while {_size(available)} are available: the run may run out of memory; "
                      f"{MEMORY_ADVICE}", RuntimeWarning, stacklevel=3)


def kalman_forward(lin: LinearisedModel, observations, theta_mean=None, theta_cov=None, *, safeguards=None,
                   check_every_frame: bool = True, monitor_nis: bool = False, label: int = 0,
                   store=True, every: int = 1) -> ForwardPass:
    """The forward (filter) half of :func:`smooth`.

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
    :func:`covariance_interval`).
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


def _transpose_step(A, M, lt, nr):
    """``F^T lambda`` for F = [[A, M], [0, I]]."""
    out = np.empty_like(lt)
    out[:nr] = np.asarray(A.T @ lt[:nr]).ravel()
    out[nr:] = M.T @ lt[:nr] + lt[nr:]
    return out


def _transpose_columns(A, M, W, nr):
    """``F^T W`` for F = [[A, M], [0, I]] and an (n, r) W, column by column as :func:`_transpose_step`."""
    out = np.empty_like(W)
    out[:nr] = np.asarray(A.T @ W[:nr])
    out[nr:] = M.T @ W[:nr] + W[nr:]
    return out


def _dense(H):
    """H as a dense array (a sparse observation matrix densified)."""
    return H.toarray() if sp.issparse(H) else np.asarray(H)


def _congruence_step(A, M, Lam, nr):
    """``F^T Lambda F`` for F = [[A, M], [0, I]], exactly symmetric."""
    Lrr, Lrt, Ltt = Lam[:nr, :nr], Lam[:nr, nr:], Lam[nr:, nr:]
    At = A.T
    AtL = np.asarray(At @ Lrr)
    out = np.empty_like(Lam)
    rr = np.asarray(At @ AtL.T)
    out[:nr, :nr] = 0.5 * (rr + rr.T)
    if Lam.shape[0] > nr:
        LM = Lrr @ M + Lrt
        rt = np.asarray(At @ LM)
        out[:nr, nr:] = rt
        out[nr:, :nr] = rt.T
        tt = M.T @ LM + Lrt.T @ M + Ltt
        out[nr:, nr:] = 0.5 * (tt + tt.T)
    return out


def smooth(lin: LinearisedModel, observations, theta_mean=None, theta_cov=None, *, outputs=None,
           covariance: bool = False, safeguards=None, check_every_frame: bool = True, monitor_nis: bool = False,
           label: int = 0, every: int | None = None) -> SmoothedPass:
    """Kalman filter forward, modified Bryson-Frazier (RTS) smoother backward (module docstring).

    Parameters
    ----------
    lin : LinearisedModel
    observations : (n_frames, m) array
        NaN where a value is missing (those rows are left out of their frame's update).
    theta_mean, theta_cov : arrays, optional
        The prior of theta for this pass (default the model's, ``lin.theta0`` and
        ``lin.P_theta0``); a Levenberg-Marquardt step tightens it about the linearisation.
    outputs : dict, optional
        ``{name: (k, n_r) matrix}`` linear functions of ``xi`` whose smoothed variances are wanted
        (``covariance=True``), e.g. nodal displacements or strains via
        :meth:`LinearisedModel.output_in_xi`.
    covariance : bool
        Run the covariance recursion (O(n^2 (m + p)) a frame) and return the outputs' smoothed
        variances: the outputs' rows are split into blocks that read disjoint columns of xi
        (:func:`_output_blocks`), and a block of c columns and r distinct rows costs
        O(c n k + r c^2) a frame, k the rank of the information matrix (the rows observed from
        the frame on, at most n: module docstring); otherwise means only, from a pass that keeps
        no covariance. The covariance of theta is returned either way (for static parameters it
        is the forward pass's last).
    safeguards, check_every_frame, monitor_nis :
        See :func:`kalman_forward`.
    every : int, optional
        With ``covariance`` (ignored without): frames between the prior covariances kept
        (:func:`kalman_forward`); default :func:`covariance_interval`, 1 where every frame's fit
        the available memory.
        The same numbers whatever it is.
    """
    if covariance and every is None:
        every = covariance_interval(lin.dim_state, lin.n_frames,
                                    observed=int(np.sum(~np.isnan(np.asarray(observations, float)))))
    fwd = kalman_forward(lin, observations, theta_mean, theta_cov, safeguards=safeguards,
                         check_every_frame=check_every_frame, monitor_nis=monitor_nis, label=label,
                         store="covariance" if covariance else "mean", every=every if covariance else 1)
    return smooth_backward(lin, fwd, outputs=outputs, covariance=covariance)


def smooth_backward(lin: LinearisedModel, forward: ForwardPass, *, outputs=None,
                    covariance: bool = False) -> SmoothedPass:
    """The backward half of :func:`smooth`, on a :func:`kalman_forward` pass.

    On a pass run with ``store="mean"`` the smoothed means come from the adjoint ``lambda~_t``
    alone (no prior covariance of any frame): the smoothed initial state ``x_0- - P_0- lambda~_0``
    and the smoothed process noise ``w_t-1|T = -Q lambda~_t`` (the disturbance smoother, de Jong
    1988; Durbin & Koopman 2012, sec. 4.5.3) give the trajectory forward,
    ``x_t|T = F_t-1 x_t-1|T + w_t-1|T`` (after a safeguard's repair D of a frame's covariance,
    from ``x_t-1|T - D lambda_t-1``), the same as ``x_t- - P_t- lambda~_t`` to round-off for
    transitions that do not expand (the models' damped ones: round-off grows with the powers of
    an expanding F). Covariances need ``store="covariance"``.
    """
    nr = lin.n_restart
    eng = forward.engine
    if eng.store == "none":
        raise ValueError("forward: expected a pass run with store='covariance' or 'mean' (it keeps what the "
                         "backward pass needs)")
    if eng.store == "mean":
        if covariance:
            raise ValueError("forward: covariance=True needs a pass run with store='covariance' (the prior "
                             "covariance of every frame); this one kept the means' part only")
        return _smooth_means(lin, forward)
    T, n = lin.n_frames, lin.dim_state
    lam = np.zeros(n)
    # Lambda as a factor W W^T while its rank (the observations after the frame) is below n, then dense
    W = np.zeros((n, 0)) if covariance else None
    Lam = None
    outputs = _checked_outputs(outputs, nr) if covariance else {}
    groups = _output_blocks(outputs)
    var = {name: np.zeros((T, L.shape[0])) for name, L in outputs.items()}
    smoothed = np.empty((T, n))
    segment: dict = {}
    for t in range(T - 1, -1, -1):
        if t in eng.priors:
            xb, Pb = eng.priors[t]
        else:
            if t not in segment:
                segment = _replay(lin, eng, t - t % eng.every, t)     # one segment's priors at a time
            xb, Pb = segment.pop(t)
        lt, LamT, WT = lam, Lam, W
        if t in eng.updates:
            mask, e, cho, K, _ = eng.updates[t]
            H = lin.H[mask]
            Sie = sla.cho_solve(cho, e)
            lt = lam.copy()
            lt[:nr] -= H.T @ (K.T @ lam + Sie)
            if covariance and W is not None and W.shape[1] + len(e) >= FACTOR_RANK * n:
                Lam, W, WT = W @ W.T, None, None                         # the factor is no longer the cheaper
            if covariance and W is not None:
                # (I - K H)^T W W^T (I - K H) + H^T S^-1 H = W~ W~^T, W~ = [(I - K H)^T W, H^T L^-T]
                WT = np.empty((n, W.shape[1] + len(e)))
                WT[:, :W.shape[1]] = W
                WT[:nr, :W.shape[1]] -= H.T @ (K.T @ W)
                WT[:, W.shape[1]:] = 0.0
                WT[:nr, W.shape[1]:] = sla.solve_triangular(cho[0], _dense(H), lower=True).T
            elif covariance:
                G = Lam @ K
                GH = G @ H
                LamT = Lam.copy()
                LamT[:, :nr] -= GH
                LamT[:nr, :] -= GH.T
                LamT[:nr, :nr] += H.T @ ((K.T @ G) @ H + sla.cho_solve(cho, H))
                LamT = 0.5 * (LamT + LamT.T)
        smoothed[t] = xb - Pb @ lt
        for cols, rows, members in groups:
            PC = Pb[cols, :]
            if WT is not None:
                PW = PC @ WT
                Ps = Pb[np.ix_(cols, cols)] - PW @ PW.T                 # smoothed covariance of the block's columns
            else:
                Ps = Pb[np.ix_(cols, cols)] - (PC @ LamT) @ PC.T
            v = np.einsum("ij,ij->i", rows @ Ps, rows)
            for name, where, which in members:
                var[name][t, where] = v[which]
        if t > 0:
            A, M = lin.A_at(t - 1), lin.M[t - 1]
            lam = _transpose_step(A, M, lt, nr)
            if covariance and WT is not None:
                W = _transpose_columns(A, M, WT, nr)
            elif covariance:
                Lam = _congruence_step(A, M, LamT, nr)
    # theta is static: its smoothed covariance is that of the last frame's filter (the whole cycle)
    return SmoothedPass(forward=forward, smoothed=smoothed, theta=smoothed[0, nr:].copy(),
                        P_theta=eng.P[nr:, nr:].copy(), variances=var)


def _replay(lin: LinearisedModel, eng: LinearisedEngine, start: int, stop: int) -> dict:
    """The prior means and covariances of frames ``start + 1 .. stop``, recomputed from the
    checkpoint at ``start`` by the forward pass's own steps (and its repairs, where a safeguard
    made one): ``{frame: (x, P)}``."""
    again = LinearisedEngine(lin, lin.theta0, lin.P_theta0, store="none")
    again.reset(*eng.priors[start])
    y, out = eng.observations, {}
    for t in range(start, stop):
        if t in eng.updates:
            again.update(y[t], t, eng.updates[t][0])
        if t in eng.repaired:
            again.reset(*eng.repaired[t])
        again.predict(t)
        out[t + 1] = (again.x.copy(), again.P.copy())
    return out


def _smooth_means(lin: LinearisedModel, forward: ForwardPass) -> SmoothedPass:
    """Smoothed means of a ``store="mean"`` pass: the adjoint backward, then the trajectory
    forward from the smoothed initial state under the smoothed process noise
    (:func:`smooth_backward`)."""
    nr, eng = lin.n_restart, forward.engine
    T, n = lin.n_frames, lin.dim_state
    adjoint = np.empty((T, n))
    carried = {}                                   # lambda_t = F^T lambda~_t+1 at repaired frames
    lam = np.zeros(n)
    for t in range(T - 1, -1, -1):
        if t in eng.repaired:
            carried[t] = lam.copy()
        lt = lam
        if t in eng.updates:
            mask, e, cho, K, _ = eng.updates[t]
            H = lin.H[mask]
            lt = lam.copy()
            lt[:nr] -= H.T @ (K.T @ lam + sla.cho_solve(cho, e))
        adjoint[t] = lt
        if t > 0:
            lam = _transpose_step(lin.A_at(t - 1), lin.M[t - 1], lt, nr)
    x0, P0 = eng.initial
    smoothed = np.empty((T, n))
    smoothed[0] = x0 - P0 @ adjoint[0]
    for t in range(1, T):
        prev = smoothed[t - 1]
        if t - 1 in eng.repaired:
            # a repair D of the filtered covariance at t-1 moves the next prior by F D F^T, and so
            # the step: x_t|T = F (x_t-1|T - D lambda_t-1) + w_t-1|T (the covariance pass's numbers)
            prev = prev - eng.repaired[t - 1] @ carried[t - 1]
        xr = np.asarray(lin.A_at(t - 1) @ prev[:nr]).ravel() + lin.c[t - 1] - lin.Q @ adjoint[t, :nr]
        if lin.n_params:
            xr += lin.M[t - 1] @ (prev[nr:] - lin.theta_bar)
        smoothed[t, :nr], smoothed[t, nr:] = xr, prev[nr:]
    return SmoothedPass(forward=forward, smoothed=smoothed, theta=smoothed[0, nr:].copy(),
                        P_theta=eng.P[nr:, nr:].copy())


def _checked_outputs(outputs, nr: int) -> dict:
    """The output operators as dense (k, nr) float arrays (sparse ones densified); a ValueError
    names an output of another shape."""
    out = {}
    for name, L in (outputs or {}).items():
        L = L.toarray() if sp.issparse(L) else np.asarray(L, float)
        if L.ndim != 2 or L.shape[1] != nr:
            raise ValueError(f"outputs: expected (k, {nr}) matrices on xi, got {name!r} with shape {L.shape}")
        out[name] = L
    return out


def _output_blocks(outputs) -> list:
    """The outputs' rows in blocks that read disjoint columns of xi, each block's distinct rows once.

    Two rows are in one block when their supports (non-zero columns) are joined by a chain of
    rows sharing a column (the connected components of the bipartite row-column graph), so the
    blocks' column sets are disjoint and forming the smoothed covariance of each block's
    columns costs at most what one covariance of their union would. In vibration modes, for
    example, displacements read the modal displacements and velocities the modal velocities:
    two blocks of half the columns each, instead of every output reading all of them. Rows
    repeated within a block (an output that is a selection of another's rows) are computed
    once; rows of zeros read nothing and have variance 0.

    ``outputs``: ``{name: (k, n) array}`` (:func:`_checked_outputs`). Returns ``[(cols, rows, [(name,
    where, which), ...]), ...]``: the block's columns, its distinct rows restricted to them, and for
    each output the positions ``where`` of its rows in the block and ``which`` distinct row each one is.
    """
    names, mats = list((outputs or {}).keys()), list((outputs or {}).values())
    if not mats or not sum(m.shape[0] for m in mats):
        return []
    L = np.vstack(mats)
    owner = np.repeat(np.arange(len(mats)), [m.shape[0] for m in mats])
    position = np.concatenate([np.arange(m.shape[0]) for m in mats])
    R, C = L.shape
    B = sp.csr_matrix(L != 0, dtype=np.int8)
    graph = sp.bmat([[sp.csr_matrix((R, R), dtype=np.int8), B], [B.T, sp.csr_matrix((C, C), dtype=np.int8)]],
                    format="csr")
    _, label = connected_components(graph, directed=False)
    blocks = []
    for comp in np.unique(label[:R]):
        cols = np.flatnonzero(label[R:] == comp)
        if cols.size == 0:
            continue                                            # rows of zeros: variance 0
        in_block = np.flatnonzero(label[:R] == comp)
        rows, which = np.unique(L[np.ix_(in_block, cols)], axis=0, return_inverse=True)
        which = np.asarray(which).ravel()
        members = [(names[k], position[in_block[owner[in_block] == k]], which[owner[in_block] == k])
                   for k in np.unique(owner[in_block])]
        blocks.append((cols, rows, members))
    return blocks


def rts_reference(lin: LinearisedModel, observations, theta_mean=None, theta_cov=None):
    """The textbook RTS smoother, dense, for tests: returns smoothed means (n_frames, n) and
    covariances (n_frames, n, n).

    Forward Kalman filter with F = [[A, M], [0, I]] formed densely; backward
    ``G_t = P_t|t F_t^T P_t+1|t^-1`` (a Cholesky solve), ``x_t|T = x_t|t + G_t (x_t+1|T - x_t+1|t)``,
    ``P_t|T = P_t|t + G_t (P_t+1|T - P_t+1|t) G_t^T``.
    """
    nr, p, T = lin.n_restart, lin.n_params, lin.n_frames
    y = np.asarray(observations, float)
    n = nr + p
    x = np.concatenate([lin.xi0, lin.theta0 if theta_mean is None else theta_mean])
    P = sla.block_diag(lin.P0, lin.P_theta0 if theta_cov is None else theta_cov)
    Hf = np.hstack([lin.H, np.zeros((lin.dim_obs, p))])
    Qf = sla.block_diag(lin.Q, np.zeros((p, p)))
    xf, Pf, xp, Pp, Fs = [], [], [None], [None], []
    for t in range(T):
        if t > 0:
            A = lin.A_at(t - 1)
            F = np.eye(n)
            F[:nr, :nr] = A.toarray() if sp.issparse(A) else A
            F[:nr, nr:] = lin.M[t - 1]
            off = np.concatenate([lin.c[t - 1] - lin.M[t - 1] @ lin.theta_bar, np.zeros(p)])
            x = F @ x + off
            P = F @ P @ F.T + Qf
            Fs.append(F)
            xp.append(x.copy())
            Pp.append(P.copy())
        mask = ~np.isnan(y[t])
        if mask.any():
            H = Hf[mask]
            S = H @ P @ H.T + lin.R[t][np.ix_(mask, mask)]
            K = sla.cho_solve(sla.cho_factor(S), H @ P).T
            x = x + K @ (y[t, mask] - H @ x)
            IKH = np.eye(n) - K @ H
            P = IKH @ P @ IKH.T + K @ lin.R[t][np.ix_(mask, mask)] @ K.T
        xf.append(x.copy())
        Pf.append(P.copy())
    xs, Ps = [None] * T, [None] * T
    xs[-1], Ps[-1] = xf[-1], Pf[-1]
    for t in range(T - 2, -1, -1):
        G = sla.cho_solve(sla.cho_factor(Pp[t + 1]), Fs[t] @ Pf[t]).T
        xs[t] = xf[t] + G @ (xs[t + 1] - xp[t + 1])
        Ps[t] = Pf[t] + G @ (Ps[t + 1] - Pp[t + 1]) @ G.T
    return np.array(xs), np.array(Ps)
