"""The paper's cyclic estimation (section 2.7): the periodic sequence fed again and again.

:class:`CyclicEKF` holds the settings of the method and has one entry point, :meth:`CyclicEKF.run`;
:func:`cyclic_estimate` is the same as a function. :func:`filter_loop` is one pass of any
engine over the sequence.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from .._validate import as_float_array, integer
from ..resources import limits_blas_threads
from .checkpoint import load_checkpoint, run_fingerprint, save_checkpoint
from .engines import ENGINES, make_engine
from .history import History
from .protocol import check_model, physical_parameters, process_profile
from .safeguards import Safeguards

__all__ = ["CyclicEKF", "CyclicResult", "cyclic_estimate", "filter_loop", "check_observations", "one_cycle_covariance"]


def check_observations(model, observations) -> np.ndarray:
    """Observations as a float array (n_frames, dim_obs), NaN allowed (missing), inf rejected."""
    return as_float_array("observations", observations, shape=(model.n_frames, model.dim_obs), allow_nan=True)


def filter_loop(engine, model, observations, loop: int = 0, history: History | None = None,
                safeguards: Safeguards | None = None):
    """One pass over the sequence: update at frame 0, then predict and update each frame.

    NaN observations are left out of their frame's update (rows of H, R and y); a frame with
    nothing observed is predict-only. With ``safeguards``, P is checked (and repaired) after
    every step and the NIS is monitored for divergence. Returns the posterior states, shape
    (n_frames, dim_state).
    """
    observations = check_observations(model, observations)
    if process_profile(model) is not None:
        raise ValueError("model: a process noise profile per frame interval (ProcessNoiseProfile) is used by the "
                         "smoother (linearise, kalman_forward, IteratedSmoother) only; the cyclic engines step with "
                         "model.Q alone: give the model without a profile")
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
    P_theta_one_cycle: np.ndarray = None   # P_theta with the cycle's information counted once

    method = "cyclic_ekf"

    @property
    def posterior_cov(self) -> np.ndarray:
        """The material covariance to report: the one-cycle one (the carried ``P_theta`` counts
        the cycle once per loop)."""
        return self.P_theta_one_cycle


@dataclass
class CyclicEKF:
    """Settings of the cyclic joint EKF (section 2.7), with one entry point :meth:`run`.

    Each loop restarts the kinematic (and effect) states at ``model.x0`` with their initial
    covariance and no cross-covariance, and carries over the material estimate and its
    covariance block. The run stops when the relative change of the physical parameters
    (:class:`sfem_filters.filtering.protocol.PhysicalParameters`: E and nu over all elements)
    between loops is below ``tol``, or after ``max_loops`` loops. A model with a fixed material
    needs one loop. Each loop counts the cycle's information once more (exactly so for a
    linear model: ``P_k^-1 = P3(0)^-1 + k J``), so the steps shrink about like 1/k;
    :func:`sfem_filters.filtering.diagnostics.material_drift` compares each loop's step with
    the carried posterior sd.

    Parameters
    ----------
    max_loops : int
        Loop limit (>= 1).
    tol : float
        Relative change of the physical parameters that ends the loops (> 0).
    engine : {"structured", "filterpy", "ud"}
        Joseph-form covariance (``"structured"``, or filterpy's own EKF) or the U-D factorised
        Bierman-Thornton filter (``"ud"``); see :data:`sfem_filters.filtering.engines.ENGINES`.
    ljung : bool
        Ljung's modification of the coupling term (Eq. 40); needs a model that estimates at
        most :data:`sfem_filters.filtering.ljung.LJUNG_MAX_PARAMS` parameters.
    safeguards : Safeguards, optional
        Covariance checks and repair, divergence monitoring (default: a fresh ``Safeguards()``
        per run). Its settings, the engine and ``ljung`` enter the checkpoint fingerprint;
        ``max_loops`` and ``tol`` are stopping rules and do not, so a finished run can be
        resumed with a larger loop limit or a tighter tolerance and continue where it stopped.
    """

    max_loops: int = 50
    tol: float = 1e-3
    engine: str = "structured"
    ljung: bool = False
    safeguards: Safeguards | None = None

    def __post_init__(self):
        if self.engine not in ENGINES:
            raise ValueError(f"engine: expected one of {sorted(ENGINES)}, got {self.engine!r}")
        integer("max_loops", self.max_loops, 1)
        try:
            ok = float(self.tol) > 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise ValueError(f"tol: expected a positive relative tolerance, got {self.tol!r}")
        if not isinstance(self.ljung, (bool, np.bool_)):
            raise TypeError(f"ljung: expected True or False, got {self.ljung!r}")
        if self.safeguards is not None and not isinstance(self.safeguards, Safeguards):
            raise TypeError(f"safeguards: expected a Safeguards, got {type(self.safeguards).__name__}")

    def trajectory_settings(self) -> dict:
        """The settings that shape the loops' numbers: the checkpoint fingerprint's part."""
        guard = self.safeguards if self.safeguards is not None else Safeguards()
        return {"method": "cyclic_ekf", "engine": self.engine, "ljung": bool(self.ljung), **guard.settings()}

    @limits_blas_threads
    def run(self, model, observations, *, progress: bool = False, checkpoint=None,
            description: str = "cyclic loops") -> CyclicResult:
        """Estimate from ``observations`` (n_frames, dim_obs), NaN where missing.

        Parameters
        ----------
        progress : bool
            Show a progress bar over loops.
        checkpoint : path, optional
            Saved (npz) after every loop; if it exists and matches this run, the run resumes
            from it and ends exactly as an uninterrupted run would.
        description : str
            Label of the progress bar.
        """
        check_model(model)
        y = check_observations(model, observations)
        safeguards = self.safeguards if self.safeguards is not None else Safeguards()
        eng = make_engine(self.engine, model, ljung=bool(self.ljung))
        nx = model.n_restart
        P0 = np.array(model.P0, float)
        theta = np.array(model.x0[nx:], float)
        P_theta = P0[nx:, nx:].copy()
        history = History()
        rel_changes: list = []
        start = 0
        fp = run_fingerprint(model, y, self.trajectory_settings())
        if checkpoint is not None and os.path.exists(checkpoint):
            state = load_checkpoint(checkpoint, fp)
            theta, P_theta = state["theta"], state["P_theta"]
            rel_changes = list(state["rel_changes"])
            history = History.from_arrays(state)
            start = int(state["loops_done"])
        n_loops = 1 if not model.estimates_material else int(self.max_loops)
        converged = (bool(rel_changes) and rel_changes[-1] < self.tol) or (not model.estimates_material and start > 0)
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
                before = physical_parameters(model, theta)
                states = filter_loop(eng, model, y, loop, history, safeguards)
                theta = eng.x[nx:].copy()
                P_theta = eng.P[nx:, nx:].copy()
                loops = loop + 1
                if model.estimates_material:
                    after = physical_parameters(model, theta)
                    rel = float(np.linalg.norm(after - before) / np.linalg.norm(after))
                    rel_changes.append(rel)
                    converged = rel < self.tol
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
                          f"(last relative change {rel_changes[-1]:.2e} > tol {self.tol:g})", RuntimeWarning)
        arrays = history.as_arrays()
        last = arrays["loop"] == arrays["loop"].max()
        return CyclicResult(states=states, P_diag=arrays["P_diag"][last], theta=theta, P_theta=P_theta,
                            loops=loops, converged=converged, rel_changes=rel_changes, history=history,
                            P_theta_one_cycle=one_cycle_covariance(P0[nx:, nx:], P_theta, loops))


def one_cycle_covariance(P_prior, P_loops, loops: int) -> np.ndarray:
    """The material covariance with the cycle's information counted once (the data-cloning correction).

    After ``k`` loops of the paper's scheme the carried covariance holds the prior and ``k``
    copies of one cycle's information, ``P_k^-1 = P_0^-1 + k J`` (exactly for a linear model,
    ``tests/filtering/test_drift.py``; Lele et al. 2007), so the posterior of one cycle is
    ``(P_0^-1 + (P_k^-1 - P_0^-1) / k)^-1``. It keeps the loops' estimate (the data-cloned one,
    near the maximum of the likelihood) and gives it the spread one cycle's data justify.
    """
    P_prior = np.asarray(P_prior, float)
    if P_prior.size == 0 or loops < 1:
        return np.asarray(P_loops, float).copy()
    I = np.eye(len(P_prior))
    A = sla.cho_solve(sla.cho_factor(P_prior), I)
    B = sla.cho_solve(sla.cho_factor(0.5 * (P_loops + P_loops.T)), I)
    info = A + (B - A) / float(loops)
    out = sla.cho_solve(sla.cho_factor(0.5 * (info + info.T)), I)
    return 0.5 * (out + out.T)


def cyclic_estimate(model, observations, *, max_loops: int = 50, tol: float = 1e-3,
                    engine: str = "structured", progress: bool = False, checkpoint=None,
                    description: str = "cyclic loops", safeguards: Safeguards | None = None,
                    ljung: bool = False) -> CyclicResult:
    """Feed the periodic sequence again and again until the material converges (section 2.7).

    ``CyclicEKF(max_loops, tol, engine, ljung, safeguards).run(model, observations, ...)``:
    see :class:`CyclicEKF` for the method and every setting.

    Parameters
    ----------
    observations : (n_frames, dim_obs) array
        Measurements in m (m/s for velocity rows); NaN marks a missing value.
    """
    settings = CyclicEKF(max_loops=max_loops, tol=tol, engine=engine, ljung=ljung, safeguards=safeguards)
    return settings.run(model, observations, progress=progress, checkpoint=checkpoint, description=description)
