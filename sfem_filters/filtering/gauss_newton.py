"""The Gauss-Newton loop of the iterated smoother: damped steps of the material, the trajectory
projected out.

:func:`gauss_newton_fit` is one run of :class:`~sfem_filters.filtering.iterated.IteratedSmoother`
at the model's noise (the module docstring of :mod:`sfem_filters.filtering.iterated` says what it
does and why). Every candidate theta is scored by the profile MAP cost ``J_p(theta) = min_r J``,
one linear filter pass with theta held fixed (:func:`~sfem_filters.filtering.curvature.profile_pass`);
one undamped pass of the model linearised at the last accepted theta's optimal trajectory gives
the Gauss-Newton quadratic model (:func:`~sfem_filters.filtering.curvature.gauss_newton_pass`),
which :class:`StructuredSecant` corrects by the curvature Gauss-Newton leaves out. Steps are
damped (Levenberg-Marquardt, Nielsen's rule), searched along a line when rejected and extended when
the cost falls by more than predicted; the run stops by :func:`step_in_sd` (the step of the
physical material in its posterior sd), by the cost, or by the damping.
"""
from __future__ import annotations

import os
import time
import warnings

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from .._validate import as_float_array
from .checkpoint import load_checkpoint, run_fingerprint, save_checkpoint
from .curvature import gauss_newton_pass, optimal_trajectory, profile_pass
from .cyclic import check_observations
from .history import History
from .laplace import SmootherResult, laplace_at_mode
from .linearised import check_static_parameters
from .map_cost import InverseRoot, open_loop
from .protocol import check_model, parameter_prior, physical_jacobian, physical_parameters
from .safeguards import Safeguards

__all__ = ["gauss_newton_fit", "step_in_sd", "StructuredSecant", "EXTRAPOLATE_GAIN", "EXTRAPOLATE_DECREMENT"]

#: An accepted full step whose actual decrease is at least this many times the predicted one ...
EXTRAPOLATE_GAIN = 1.25
#: ... while the quadratic model predicts less than this much more (nats) is extended
#: (:class:`~sfem_filters.filtering.iterated.IteratedSmoother` ``max_extrapolation``).
EXTRAPOLATE_DECREMENT = 1.0


def step_in_sd(step, P_theta, jacobian=None) -> float:
    """The largest move of a physical quantity in its posterior standard deviations.

    ``max_i |j_i @ step| / sqrt(j_i P j_i^T)`` over the rows ``j_i`` of ``jacobian`` (d physical
    quantity / d theta, :class:`sfem_filters.filtering.protocol.PhysicalJacobian`; ``None``: the
    parameters themselves). A row's scale cancels, and so does any invertible recombination of
    the parameters (renumbered regions, rotated contrasts or basis modes): the rule judges the
    material, not its coordinates. Rows that do not move with theta are left out.

    Parameters
    ----------
    step : (p,) array
        Step in theta.
    P_theta : (p, p) array
        Posterior covariance of theta.
    jacobian : (q, p) array or sparse matrix, optional
        Rows of the physical quantities' derivatives.

    Returns
    -------
    float
        The largest move in sd (0 when no row moves with theta).
    """
    step = as_float_array("step", step, shape=(None,))
    p = len(step)
    P = as_float_array("P_theta", P_theta, shape=(p, p))
    if jacobian is None:
        return float(np.max(np.abs(step) / np.sqrt(np.diag(P))))
    J = sp.csr_matrix(jacobian)
    if J.shape[1] != p:
        raise ValueError(f"jacobian: expected {p} columns (one per parameter), got shape {J.shape}")
    scale = np.asarray(abs(J).max(axis=1).todense(), float).ravel()
    keep = scale > 0.0
    if not np.any(keep):
        return 0.0
    J = sp.diags(1.0 / scale[keep]) @ J[keep]           # rows of unit size: their scale cancels anyway
    moved = np.abs(J @ step)
    var = np.asarray(J.multiply(J @ P).sum(axis=1)).ravel()
    return float(np.max(moved / np.sqrt(np.maximum(var, np.finfo(float).tiny))))



class StructuredSecant:
    """The curvature Gauss-Newton leaves out, learnt from gradients (Dennis, Gay & Welsch 1981).

    The profile cost's Hessian is the Gauss-Newton part (the smoother's) plus the residuals times
    their second derivatives, which matters when the model does not fit the data (large
    residuals). After a step ``s`` the gradient changes by ``y``; the change the new
    Gauss-Newton Hessian does not explain, ``y# = y - H_GN s``, updates the correction ``S`` by
    the least symmetric change that satisfies ``S s = y#`` (NL2SOL's update, with its sizing of
    the old ``S``). Skipped when ``y^T s <= 0``.
    """

    def __init__(self, p: int):
        self.S = np.zeros((p, p))
        self.s = self.g = None

    def taken(self, step, g):
        """Record the step just taken and the gradient where it started, for the next :meth:`update`.

        Parameters
        ----------
        step : (p,) array
            The step taken in theta.
        g : (p,) array
            The gradient of the profile cost before the step.
        """
        self.s, self.g = np.array(step, float), np.array(g, float)

    def state(self) -> dict:
        """Arrays for a checkpoint (``s`` and ``g`` empty before the first step)."""
        empty = np.zeros(0)
        return {"secant_S": self.S, "secant_s": empty if self.s is None else self.s,
                "secant_g": empty if self.g is None else self.g}

    def restore(self, state) -> None:
        """Set the correction and the last step from a checkpoint.

        Parameters
        ----------
        state : mapping
            The arrays of :meth:`state` (``secant_S``, ``secant_s``, ``secant_g``).
        """
        self.S = np.array(state["secant_S"], float)
        if np.size(state["secant_s"]):
            self.s, self.g = np.array(state["secant_s"], float), np.array(state["secant_g"], float)

    def update(self, H, g) -> np.ndarray:
        """Update the correction ``S`` with the gradient change since the last step, and return it.

        Skipped before the first step and when ``y^T s <= 0`` (``s`` the last step, ``y`` the gradient's change).

        Parameters
        ----------
        H : (p, p) array
            The Gauss-Newton Hessian at the new point.
        g : (p,) array
            The gradient of the profile cost at the new point.

        Returns
        -------
        (p, p) array
            The symmetric correction ``S``: ``H + S`` models the full Hessian.
        """
        if self.s is not None:
            s, y = self.s, g - self.g
            ys = float(y @ s)
            if ys > 0:
                ysharp = y - H @ s
                sSs = float(s @ self.S @ s)
                if sSs != 0:
                    self.S *= min(1.0, abs(float(s @ ysharp)) / abs(sSs))
                r = ysharp - self.S @ s
                self.S = self.S + (np.outer(r, y) + np.outer(y, r)) / ys - float(r @ s) * np.outer(y, y) / ys ** 2
                self.S = 0.5 * (self.S + self.S.T)
        return self.S


def gauss_newton_fit(settings, model, observations, *, progress: bool = False, checkpoint=None,
                     description: str = "iterated smoother", start=None) -> SmootherResult:
    """One run at the model's Q (module docstring), with the Laplace posterior at its end.

    Parameters
    ----------
    settings : IteratedSmoother
        The run's settings (:class:`~sfem_filters.filtering.iterated.IteratedSmoother`: its
        stopping rules, damping, extrapolation, safeguards and ``covariance``).
    model, observations :
        As for :meth:`~sfem_filters.filtering.iterated.IteratedSmoother.run`.
    progress, checkpoint, description :
        A progress bar on stderr; a checkpoint path saved after every accepted iteration (an
        existing one of the same run is resumed); the bar's label.
    start : (n_frames, dim_state) array, optional
        A trajectory whose material is the first iterate instead of the prior mean.

    Returns
    -------
    SmootherResult
    """
    check_model(model)
    p = check_static_parameters(model)
    y = check_observations(model, observations)
    guard = settings.safeguards if settings.safeguards is not None else Safeguards()
    nr = int(model.n_restart)
    theta0, P3 = parameter_prior(model)
    fp = run_fingerprint(model, y, settings.trajectory_settings())
    records: list = []

    P3_root = InverseRoot(P3) if p else None

    def profile(theta, like):
        """J_p(theta) = min over the trajectory of J, by one linear filter pass with theta held
        fixed (completing the square: the minimum is half the summed NIS plus theta's prior
        term), with what the backward pass needs to recover the optimal trajectory."""
        fit, found = profile_pass(model, y, theta, like, guard, label=len(records))
        return fit + (0.5 * P3_root.norm2(theta - theta0) if p and found is not None else 0.0), found

    secant = StructuredSecant(p)
    if checkpoint is not None and os.path.exists(checkpoint):
        state = load_checkpoint(checkpoint, fp)
        secant.restore(state)
        z, lam, nu = np.array(state["trajectory"]), float(state["damping"]), float(state["nu"])
        records = [dict(zip(state["record_keys"].tolist(), map(float, row))) for row in state["records"]]
        cost, stop = float(state["cost"]), str(state["stop_reason"])
    else:
        lam, nu, stop = float(settings.damping), 2.0, ""
        cost, found = (np.inf, None) if start is None else profile(np.asarray(start, float)[0, nr:], start)
        if found is None or not np.isfinite(cost):
            cost, found = profile(theta0, open_loop(model))
        if found is None or not np.isfinite(cost):
            raise FloatingPointError("the prior's material gives no finite MAP cost: the model cannot step its "
                                     "initial state")
        z = optimal_trajectory(model, found)
    if p == 0:
        stop = "no parameters"
    bar = None
    if progress and not stop:
        from tqdm import tqdm
        bar = tqdm(total=settings.max_iterations, initial=len(records), desc=description, unit="it", leave=False)
    try:
        P3_inv = sla.cho_solve(sla.cho_factor(P3), np.eye(p)) if p else None
        while not stop and len(records) < settings.max_iterations:
            t0 = time.perf_counter()
            theta_bar = z[0, nr:]
            # One undamped pass of the linearised model gives the Gauss-Newton quadratic model
            # of the profile cost about theta_bar: its Hessian is the inverse of the pass's
            # posterior covariance of theta, and its gradient is exact (the linearisation is
            # exact to first order and the trajectory part is at its optimum). Damped steps and
            # rejections are then p x p solves, not further passes.
            g, H, P_theta = gauss_newton_pass(model, y, z, guard, label=len(records))
            S = secant.update(H, g)
            H_model = H + S
            try:
                cho_model = sla.cho_factor(H_model, lower=True)
            except np.linalg.LinAlgError:
                # the secant correction made the model indefinite: drop it rather than let the
                # damping grow to cover it (a large lambda shortens the steps, not the distance)
                secant.S[:] = 0.0
                H_model = H
                cho_model = sla.cho_factor(H, lower=True)
            # the undamped step of the quadratic model and its predicted decrease (the Newton
            # decrement): how far the mode still is, whatever the damping does to the step taken
            full = -sla.cho_solve(cho_model, g)
            J = physical_jacobian(model, theta_bar)
            full_sd = step_in_sd(full, P_theta, J)
            newton_decrement = float(-0.5 * g @ full)
            rejected = 0
            while True:
                try:
                    step = -sla.cho_solve(sla.cho_factor(H_model + lam * P3_inv, lower=True), g)
                except np.linalg.LinAlgError:
                    lam, nu = max(lam, 1e-3) * nu, 2.0 * nu
                    continue
                predicted = -(g @ step + 0.5 * step @ H_model @ step)
                lam_used, alpha = lam, 1.0
                new_cost, found = profile(theta_bar + step, z)
                gain = (cost - new_cost) / max(predicted, 1e-300)
                if new_cost < cost:
                    # Nielsen's factor; a gain ratio >= 1 (also a vanishing predicted decrease,
                    # where the ratio overflows) gives its floor 1/3
                    lam *= 1.0 / 3.0 if gain >= 1.0 else max(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
                    nu = 2.0
                    break
                # line search: the minimum of the quadratic through J(0), J'(0) and J(1), in [0.1, 0.5]
                slope = g @ step
                curv = new_cost - cost - slope if np.isfinite(new_cost) else np.inf
                alpha = float(np.clip(-slope / (2.0 * curv), 0.1, 0.5)) if curv > 0 else 0.1
                new_cost, found = profile(theta_bar + alpha * step, z)
                if new_cost < cost:
                    lam *= 2.0
                    break
                rejected += 1
                if lam >= settings.max_damping:
                    # no damping lowers the cost: the end, converged only if the model also
                    # predicts no worthwhile decrease (else the run is stuck, and says so)
                    stop = "cost" if newton_decrement < settings.cost_tol else "damping"
                    break
                lam, nu = max(lam, 1e-3) * nu, 2.0 * nu
            if stop:
                break
            if (alpha == 1.0 and gain >= EXTRAPOLATE_GAIN and newton_decrement < EXTRAPOLATE_DECREMENT
                    and settings.max_extrapolation > 1.0):
                # the cost fell by more than the model predicted, and the model predicts
                # little more: its curvature along the step is too large (a plateau the
                # Gauss-Newton model cannot see), so the mode lies further along; double the
                # step while the cost keeps falling
                factor = 2.0
                while factor <= settings.max_extrapolation:
                    trial_cost, trial_found = profile(theta_bar + factor * step, z)
                    if not trial_cost < new_cost:
                        break
                    new_cost, found, alpha = trial_cost, trial_found, factor
                    factor *= 2.0
            taken = alpha * step
            secant.taken(taken, g)
            before = physical_parameters(model, theta_bar)
            moved, size = np.linalg.norm(physical_parameters(model, theta_bar + taken) - before), np.linalg.norm(before)
            rel = float(moved / size) if size > 0 else np.inf    # no relative change from zero parameters
            step_sd = step_in_sd(taken, P_theta, J)
            records.append({"iteration": len(records) + 1, "cost": new_cost, "decrease": cost - new_cost,
                            "damping": lam_used, "step_length": alpha, "gain_ratio": float(gain), "rejected": rejected,
                            "rel_change": rel, "step_sd": step_sd, "max_abs_step": float(np.max(np.abs(taken))),
                            "full_step_sd": full_sd, "newton_decrement": newton_decrement, "seconds": 0.0})
            z, cost = optimal_trajectory(model, found), new_cost
            records[-1]["seconds"] = time.perf_counter() - t0
            # the rules judge the undamped step too: a step shortened by a large lambda says
            # nothing about the distance to the mode
            if rel < settings.tol and step_sd < settings.sd_tol and full_sd < settings.sd_tol:
                stop = "step"
            elif records[-1]["decrease"] < settings.cost_tol and newton_decrement < settings.cost_tol:
                stop = "cost"
            if checkpoint is not None:
                keys = list(records[0])
                save_checkpoint(checkpoint, fp, z[0, nr:], P3, [r["rel_change"] for r in records], History(),
                                len(records), trajectory=z, damping=lam, nu=nu, cost=cost, stop_reason=stop,
                                **secant.state(),
                                record_keys=np.array(keys), records=np.array([[r[k] for k in keys]
                                                                              for r in records]))
            if bar is not None:
                bar.update(1)
                bar.set_postfix(cost=f"{cost:.6g}", damping=f"{records[-1]['damping']:.0e}",
                                step_sd=f"{step_sd:.2g}")
    finally:
        if bar is not None:
            bar.close()
    if not stop:
        stop = "max_iterations"
    converged = stop in ("step", "cost", "no parameters")
    if not converged:
        warnings.warn(f"iterated smoother: stopped by '{stop}' after {len(records)} iterations before the "
                      f"material step met the rule (tol {settings.tol:g}, {settings.sd_tol:g} sd)", RuntimeWarning)
    return laplace_at_mode(model, y, z, cost, records, stop, converged, guard, covariance=settings.covariance)
