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
"""
from __future__ import annotations

import hashlib
import os
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from filterpy.kalman import ExtendedKalmanFilter

from ._validate import as_float_array

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

    def predict_x(self, u=0):
        """Propagate x from frame ``u`` (an int) to frame ``u + 1`` and set F there."""
        t = int(u)
        self.F = self.model.F_jacobian(self.x, t)
        self.x = self.model.fx(self.x, t)

    def predict_update(self, z, HJacobian, Hx, args=(), hx_args=(), u=0):
        """``predict(u)`` then ``update(z, ...)``: filterpy's own version would use F x, not fx."""
        self.predict(u)
        self.update(z, HJacobian, Hx, args=args, hx_args=hx_args)


class FilterpyEngine:
    """Runs the filter through :class:`SFEMExtendedKalmanFilter` (the reference)."""

    def __init__(self, model):
        self.model = model
        self.ekf = model.make_ekf()

    def reset(self, x, P):
        self.ekf.x = np.asarray(x, float).reshape(-1, 1).copy()
        self.ekf.P = np.array(P, float)

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
        R = m.R[np.ix_(mask, mask)]
        self.ekf.update(y[mask].reshape(-1, 1), lambda x, tt: H,
                        lambda x, tt: m.hx(x, tt)[mask], R=R, args=t, hx_args=t)
        return self.ekf.y.ravel(), self.ekf.S


class StructuredEngine:
    """The same filter exploiting F = [[A, M_t], [0, I]] and a Cholesky-factored S."""

    def __init__(self, model):
        self.model = model
        self._x = np.asarray(model.x0, float).copy()
        self._P = np.array(model.P0, float)

    def reset(self, x, P):
        self._x = np.asarray(x, float).ravel().copy()
        self._P = np.array(P, float)

    @property
    def x(self):
        return self._x

    @property
    def P(self):
        return self._P

    def predict(self, t):
        m = self.model
        nx = m.n_restart        # F = [[A', M'], [0, I]] with A' over kinematics and effect states
        F = m.F_jacobian(self._x, t)
        A, Mt = F[:nx, :nx], F[:nx, nx:]
        P = self._P
        Pxx, Pxt, Ptt = P[:nx, :nx], P[:nx, nx:], P[nx:, nx:]
        new = np.empty_like(P)
        APxt = A @ Pxt
        cross = APxt + Mt @ Ptt
        new[:nx, :nx] = A @ Pxx @ A.T + APxt @ Mt.T + (APxt @ Mt.T).T + Mt @ Ptt @ Mt.T
        new[:nx, nx:] = cross
        new[nx:, :nx] = cross.T
        new[nx:, nx:] = Ptt
        self._P = new + m.Q
        self._x = m.fx(self._x, t)

    def update(self, y, t, mask):
        m = self.model
        H = m.H_jacobian(self._x, t)[mask]
        R = m.R[np.ix_(mask, mask)]
        PHt = self._P @ H.T
        S = H @ PHt + R
        cho = sla.cho_factor(S, lower=True)
        K = sla.cho_solve(cho, PHt.T).T
        innov = y[mask] - m.hx(self._x, t)[mask]
        self._x = self._x + K @ innov
        # Joseph form (I - KH) P (I - KH)^T + K R K^T, expanded so that it costs O(n^2 m):
        # P - K (H P) - (H P)^T K^T + K S K^T
        KHP = K @ PHt.T
        P = self._P - KHP - KHP.T + (K @ S) @ K.T
        self._P = 0.5 * (P + P.T)
        return innov, S


ENGINES = {"filterpy": FilterpyEngine, "structured": StructuredEngine}


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

    def check_covariance(self, engine, loop, t):
        P = engine.P
        try:
            np.linalg.cholesky(0.5 * (P + P.T))
            return
        except np.linalg.LinAlgError:
            pass
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


def _fingerprint(model, observations, engine: str, max_loops, tol) -> str:
    """Hash of everything that determines a run: the model's own fingerprint when it has one
    (mechanics, loads, material, parameterisation, effects), the filter set-up and the data."""
    h = hashlib.sha256()
    if hasattr(model, "fingerprint"):
        h.update(model.fingerprint().encode())
    for a in (model.x0, model.P0, model.Q, model.R, np.nan_to_num(observations, nan=1e300),
              model.H_jacobian(model.x0, 0)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(f"{model.dim_state},{model.n_frames},{engine},{tol!r}".encode())
    return h.hexdigest()


def _physical(model, theta):
    mat = model.material_of_theta(theta)
    return np.concatenate([mat.E, mat.nu])


def cyclic_estimate(model, observations, *, max_loops: int = 50, tol: float = 1e-3,
                    engine: str = "structured", progress: bool = False, checkpoint=None,
                    description: str = "cyclic loops", safeguards: Safeguards | None = None) -> CyclicResult:
    """Feed the periodic sequence again and again until the material converges (section 2.7).

    Each loop restarts the kinematic (and effect) states at ``model.x0`` with their initial
    covariance and no cross-covariance, and carries over the material estimate and its
    covariance block. The
    run stops when the relative change of (E, nu) over all elements (physical units) between
    loops is below ``tol`` or after ``max_loops`` loops. A model with a fixed material needs
    one loop.

    Parameters
    ----------
    observations : (n_frames, dim_obs) array
        Measurements in m; NaN marks a missing value.
    engine : {"structured", "filterpy"}
    progress : bool
        Show a progress bar over loops.
    checkpoint : path, optional
        Saved (npz) after every loop; if it exists and matches this run, the run resumes
        from it and ends exactly as an uninterrupted run would.
    safeguards : Safeguards, optional
        Covariance checks and repair, divergence monitoring (default: ``Safeguards()``).
    """
    if engine not in ENGINES:
        raise ValueError(f"engine: expected one of {sorted(ENGINES)}, got {engine!r}")
    if int(max_loops) != max_loops or max_loops < 1:
        raise ValueError(f"max_loops: expected an integer >= 1, got {max_loops!r}")
    if not tol > 0:
        raise ValueError(f"tol: expected a positive relative tolerance, got {tol!r}")
    y = _check_observations(model, observations)
    safeguards = Safeguards() if safeguards is None else safeguards
    eng = ENGINES[engine](model)
    nx = model.n_restart
    P0 = np.array(model.P0, float)
    theta = np.array(model.x0[nx:], float)
    P_theta = P0[nx:, nx:].copy()
    history = History()
    rel_changes: list = []
    start = 0
    fp = _fingerprint(model, y, engine, max_loops, tol)
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
