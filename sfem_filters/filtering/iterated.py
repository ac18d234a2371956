"""The iterated extended Kalman smoother: Gauss-Newton on the MAP of one cycle, damped.

The unknowns are the restart trajectory ``r_0..r_T`` (kinematics and effect states) and the
static parameters theta (material); the data of the cycle are counted once. The negative log
posterior (the MAP cost) is

    J = 1/2 |r_0 - x0|^2_{P1^-1} + 1/2 |theta - theta0|^2_{P3^-1}
        + 1/2 sum_t |r_{t+1} - f_r(r_t, theta, t)|^2_{Q^-1} + 1/2 sum_t |y_t - H r_t|^2_{R_t^-1}.

Bell (1994, SIAM J. Optim. 4:626) showed that smoothing the model linearised about a trajectory
(:mod:`sfem_filters.filtering.linearised`, :func:`sfem_filters.filtering.smoother.smooth`) is
exactly a Gauss-Newton step on J. Two things make the steps robust:

* **The trajectory is projected out.** For a fixed theta the model is linear in the trajectory
  (``f_r = A(theta) r + B(theta) w``), so the best trajectory for a theta, and with it the
  profile cost ``J_p(theta) = min_r J``, is one linear smoother pass with theta held fixed
  (variable projection, Golub & Pereyra 1973). Every candidate theta is scored by ``J_p`` and
  the next linearisation is taken at its optimal trajectory; a step is never judged by a
  trajectory the old theta's linearisation left behind.
* **Levenberg-Marquardt damping and a line search** (Sarkka & Svensson 2020, ICASSP,
  "Levenberg-Marquardt and line-search extended Kalman smoothers"): a step is accepted only if
  the MAP cost falls. The damping ``lambda/2 |theta - theta_bar|^2_{P3^-1}`` is a Gaussian
  pseudo-observation of ``theta_bar`` with the prior's shape, so it simply tightens the prior of
  the pass to ``N((theta0 + lambda theta_bar) / (1 + lambda), P3 / (1 + lambda))``. A failed step
  is tried at half its length, then lambda grows (Nielsen's rule, :class:`IteratedSmoother`).
  A full step that lowered the cost by more than the model predicted, where the model predicts
  little more, is doubled while the cost keeps falling (a plateau the Gauss-Newton curvature
  hides; ``max_extrapolation``).

Each iteration relinearises at the optimal trajectory of the last accepted theta and restarts
from the prior. The run stops when an accepted step moves the material by less than ``tol``
(relative, physical units) and by less than ``sd_tol`` posterior standard deviations of every
physical quantity (the step taken and the undamped one alike; :func:`step_in_sd`), when the
cost stops falling (an accepted decrease below ``cost_tol`` with a Newton decrement below it too,
or no damping makes it fall), or at ``max_iterations``. No damping lowering the cost while the
model still predicts a decrease is reported as stuck (``"damping"``), not converged. A secant
correction that makes the quadratic model indefinite is dropped instead of being covered by a
larger damping. The reported posterior is the Laplace approximation at the mode: the mode
itself, and the covariance of an undamped pass linearised there (the inverse Gauss-Newton
Hessian), with smoothed marginal variances of the kinematics and of the model's output
operators (strains).

The process noise Q is a modelling choice the data can judge. With ``process_noise="estimate"``
its level (one factor on every process noise) is chosen by maximum evidence, log p(y | factor)
with the trajectory and the material integrated out by the Laplace approximation at each
factor's mode (type-II maximum likelihood, empirical Bayes); the posterior reported is the one
at that factor. On the calibration spec's check, whose truth moves without process noise, this
is what turns a conservative posterior (the configured Q is too large for the data) into a
calibrated one (``python -m validation run calibration``).

The pieces: :mod:`~sfem_filters.filtering.map_cost` (the MAP cost J, :class:`MapObjective`, and
the prior's trajectory, :func:`open_loop`), :mod:`~sfem_filters.filtering.gauss_newton` (the
damped Gauss-Newton loop of one run, its secant correction and its stop rule, :func:`step_in_sd`),
:mod:`~sfem_filters.filtering.laplace` (the result, :class:`SmootherResult`, and the Laplace
posterior at the mode: :func:`exact_laplace`, :func:`with_covariance`), and here the settings,
:class:`IteratedSmoother`, whose :meth:`~IteratedSmoother.run` also chooses the noise levels.
"""
from __future__ import annotations

import math
import sys
import warnings
from dataclasses import dataclass, replace

import numpy as np

from .._validate import as_float_array, integer, non_negative, positive
from ..resources import limits_blas_threads
from .cyclic import check_observations
from .gauss_newton import gauss_newton_fit, step_in_sd
from .laplace import SmootherResult, exact_laplace, laplace_at_mode, with_covariance
from .map_cost import MapObjective, open_loop
from .memory import check_memory
from .protocol import check_model, scaled_measurement_noise, scaled_process_noise
from .safeguards import Safeguards

__all__ = ["IteratedSmoother", "check_noise_range", "SmootherResult", "MapObjective", "iterated_smoother", "open_loop",
           "exact_laplace", "with_covariance", "step_in_sd", "NOISE_LEVELS"]

#: How a noise level is set (``process_noise=``, ``measurement_noise=``): as the model gives it, or
#: by type-II maximum likelihood.
NOISE_LEVELS = ("fixed", "estimate")


def check_noise_range(noise_range) -> tuple:
    """``noise_range`` as ``(low, high)`` floats, ``0 < low <= 1 <= high`` (factors on Q or R), or a
    ValueError naming it (:class:`IteratedSmoother` ``noise_range``)."""
    try:
        low, high = (float(v) for v in noise_range)
    except (TypeError, ValueError):
        raise ValueError(f"noise_range: expected two factors (low, high), got {noise_range!r}") from None
    if not (0.0 < low <= 1.0 <= high < np.inf):
        raise ValueError(f"noise_range: expected 0 < low <= 1 <= high (factors on Q), got {noise_range!r}")
    return low, high


@dataclass
class IteratedSmoother:
    """Settings of the iterated extended Kalman smoother (module docstring), one entry point :meth:`run`.

    Parameters
    ----------
    max_iterations : int
        Accepted Gauss-Newton steps at most (>= 1).
    tol : float
        Relative change of the physical parameters below which a step may end the run (> 0).
    sd_tol : float
        ... and the largest move of a physical quantity in its posterior standard deviations
        (> 0; :func:`step_in_sd`, per parameter for a model without ``physical_jacobian``), for the
        step taken and for the undamped step of the quadratic model from the same point (a step
        shortened by a large damping says nothing about the distance to the mode).
    cost_tol : float
        An accepted step that lowers the MAP cost by less than this (nats, > 0), when the undamped
        quadratic model also predicts less (its Newton decrement ``g^T H^-1 g / 2``), ends the
        run: the cost has stopped falling. The default is ``sd_tol^2 / 2``, what a move of
        ``sd_tol`` posterior sd along one direction changes the cost by near the mode.
    damping : float
        Initial Levenberg-Marquardt lambda, in units of the prior precision of theta (>= 0;
        0 starts with an undamped Gauss-Newton step).
    max_damping : float
        A step rejected at this damping ends the run: converged (``"cost"``) if the undamped
        quadratic model predicts a decrease below ``cost_tol`` too, else stuck (``"damping"``,
        reported as not converged).
    covariance : bool
        Compute the smoothed marginal variances of the kinematics and of the model's output
        operators in the final pass (O(k n^2) a frame per output).
    safeguards : Safeguards, optional
        Covariance check and repair in every pass, NIS monitoring in the final one.
    process_noise : {"fixed", "estimate"}
        ``"fixed"``: the model's Q as given. ``"estimate"``: Q's level from the data, by type-II
        maximum likelihood (empirical Bayes) of one factor ``s`` on every process noise: the MAP
        of the trajectory and material is found for each ``s`` tried and scored by its evidence
        log p(y | s), the prediction-error log-likelihood of the model linearised at that mode
        (theta integrated out by the same linearisation, i.e. the Laplace evidence). ``s`` walks
        from 1 in factors of 4 (down first, then up) while the evidence rises by more than
        ``noise_tol``, then one parabolic step in log s between the best and its neighbours; each
        run starts from the previous scale's mode. The reported posterior is the one at the best
        ``s`` (plug-in: the uncertainty of ``s`` itself is not propagated). Needs a model with
        ``with_process_noise`` (:class:`~sfem_filters.filtering.protocol.ScalableProcessNoise`).
    measurement_noise : {"fixed", "estimate"}
        The same for the measurement noise: ``"estimate"`` chooses one factor on R (every frame's)
        by the same walk over factors of 4 and the same evidence (needs ``with_measurement_noise``,
        :class:`~sfem_filters.filtering.protocol.ScalableMeasurementNoise`). Where R is set from
        a floor that can hold motion as well as noise (the ``dense`` workflow's), the data judge
        the level. With both ``"estimate"``: R's level first at the model's Q, then Q's level at
        that R (one sweep of coordinate ascent, each warm-started from the previous mode).
    noise_range : (float, float)
        Smallest and largest factor on Q (and on R) tried (0 < low <= 1 <= high).
    noise_tol : float
        Evidence gain (nats, > 0) below which the walk over scales stops.
    laplace : {"gauss-newton", "exact"}
        The Hessian whose inverse is the reported covariance of theta. ``"gauss-newton"``: the
        final pass's (free). ``"exact"``: the profile cost's exact Hessian at the mode by central
        differences of its exact gradient (:func:`~sfem_filters.filtering.curvature.profile_hessian`,
        2 p more gradient passes), the Laplace approximation proper; where the model misfits its
        data the residual curvature Gauss-Newton leaves out can be large (the docs' frozen
        result of the Hessian check). Not positive definite there (a run stopped short of a minimum): a
        warning, and the Gauss-Newton covariance is kept.

    max_extrapolation : float
        Longest multiple of an accepted full step tried (>= 1; 1 turns extrapolation off). When
        the cost fell by at least :data:`~sfem_filters.filtering.gauss_newton.EXTRAPOLATE_GAIN`
        times the decrease the quadratic model predicted and the model's Newton decrement is below
        :data:`~sfem_filters.filtering.gauss_newton.EXTRAPOLATE_DECREMENT` nats, the Gauss-Newton
        curvature along the step is too large (the model misses a falling stretch of the cost, as
        on a plateau), and the step is doubled while the cost keeps falling (2, 4, 8, ...: powers
        of two up to this multiple), one profile pass per try. Near a start far from the mode (a
        large decrement) steps are not extended. The records keep
        the extended step's decrease and length, and the unextended step's gain ratio.

    The damping follows Nielsen's rule: after an accepted full step lambda is multiplied by
    ``max(1/3, 1 - (2 rho - 1)^3)``, rho the ratio of the cost's actual to its predicted decrease;
    after an accepted half step it doubles; after a rejection it grows by a factor that doubles
    with every rejection in a row. The settings that shape the iterates (damping, max_damping,
    max_extrapolation unless it is 1, the safeguards) enter the checkpoint fingerprint; the
    stopping rules (max_iterations, tol, sd_tol, cost_tol) and ``covariance`` do not, so a
    finished run can be resumed with a stricter rule.
    """

    max_iterations: int = 20
    tol: float = 1e-3
    sd_tol: float = 0.1
    cost_tol: float = 5e-3
    damping: float = 1.0
    max_damping: float = 1e8
    covariance: bool = True
    safeguards: Safeguards | None = None
    process_noise: str = "fixed"
    measurement_noise: str = "fixed"
    noise_range: tuple = (4.0 ** -8, 4.0 ** 3)
    noise_tol: float = 0.05
    laplace: str = "gauss-newton"
    max_extrapolation: float = 8.0

    def __post_init__(self):
        integer("max_iterations", self.max_iterations, 1)
        positive("tol", self.tol)
        positive("sd_tol", self.sd_tol)
        positive("cost_tol", self.cost_tol)
        non_negative("damping", self.damping)
        positive("max_damping", self.max_damping)
        if not isinstance(self.covariance, (bool, np.bool_)):
            raise TypeError(f"covariance: expected True or False, got {self.covariance!r}")
        if self.safeguards is not None and not isinstance(self.safeguards, Safeguards):
            raise TypeError(f"safeguards: expected a Safeguards, got {type(self.safeguards).__name__}")
        if self.process_noise not in NOISE_LEVELS:
            raise ValueError(f"process_noise: expected 'fixed' or 'estimate', got {self.process_noise!r}")
        if self.measurement_noise not in NOISE_LEVELS:
            raise ValueError(f"measurement_noise: expected 'fixed' or 'estimate', got {self.measurement_noise!r}")
        check_noise_range(self.noise_range)
        positive("noise_tol", self.noise_tol)
        if self.laplace not in ("gauss-newton", "exact"):
            raise ValueError(f"laplace: expected 'gauss-newton' or 'exact', got {self.laplace!r}")
        if not (isinstance(self.max_extrapolation, (int, float, np.integer, np.floating))
                and not isinstance(self.max_extrapolation, bool) and 1.0 <= float(self.max_extrapolation) < np.inf):
            raise ValueError(f"max_extrapolation: expected a finite multiple >= 1 of a step (1: never extend a "
                             f"step), got {self.max_extrapolation!r}")

    def trajectory_settings(self) -> dict:
        """The settings that shape the iterates: the checkpoint fingerprint's part (method, damping, the
        safeguards' settings, and ``max_extrapolation`` when it is not 1)."""
        guard = self.safeguards if self.safeguards is not None else Safeguards()
        out = {"method": "iterated_smoother", "damping": float(self.damping), "max_damping": float(self.max_damping),
               **guard.settings()}
        if float(self.max_extrapolation) != 1.0:
            # without extrapolation the iterates are those of earlier versions: their checkpoints resume
            out["max_extrapolation"] = float(self.max_extrapolation)
        return out

    @limits_blas_threads
    def run(self, model, observations, *, progress: bool = False, checkpoint=None,
            description: str = "iterated smoother", start=None) -> SmootherResult:
        """Estimate from one cycle's ``observations`` (n_frames, dim_obs), NaN where missing.

        ``checkpoint``: a path saved after every accepted iteration; an existing checkpoint of
        the same run is resumed and the run ends exactly as an uninterrupted one would (with
        ``process_noise="estimate"``, one checkpoint per scale tried, ``<checkpoint>.noise<k>``;
        with ``measurement_noise="estimate"``, ``<checkpoint>.Rnoise<k>``).
        ``start``: a warm start, a trajectory (n_frames, dim_state) whose material (any frame's,
        model coordinates) is the first iterate instead of the prior mean, for example another
        run's ``states``; the MAP cost, and so the mode, are unchanged. A start where the model
        cannot step falls back to the prior mean.
        """
        check_model(model)
        rows = int(np.sum(~np.isnan(check_observations(model, observations))))
        check_memory(model.dim_state, model.n_frames, covariance=self.covariance, observed=rows)   # before any pass
        if start is not None:
            start = as_float_array("start", start, shape=(model.n_frames, model.dim_state))
        if self.measurement_noise == "estimate":
            # R's level first, at the model's Q; then, if asked, Q's level at the R chosen
            inner = replace(self, covariance=self.covariance and self.process_noise == "fixed")
            first = inner._estimate_noise(model, observations, progress, checkpoint, description, start,
                                          kind="measurement")
            result = first
            if self.process_noise == "estimate":
                scaled = scaled_measurement_noise(model, first.measurement_noise_scale)
                level = math.log(first.measurement_noise_scale, 4.0)
                cp = None if checkpoint is None else f"{checkpoint}.R{level:+.4f}"
                result = self._estimate_noise(scaled, observations, progress, cp, description, first.states)
                result.measurement_noise_scale = first.measurement_noise_scale
                result.measurement_noise_search = first.measurement_noise_search
        elif self.process_noise == "estimate":
            result = self._estimate_noise(model, observations, progress, checkpoint, description, start)
        else:
            result = self._fit(model, observations, progress=progress, checkpoint=checkpoint, description=description,
                               start=start)
        if self.laplace == "exact" and result.theta.size:
            used = model
            if result.measurement_noise_scale != 1.0:
                used = scaled_measurement_noise(used, result.measurement_noise_scale)
            if result.process_noise_scale != 1.0:
                used = scaled_process_noise(used, result.process_noise_scale)
            result = exact_laplace(used, observations, result, safeguards=self.safeguards, progress=progress)
        return result

    def _estimate_noise(self, model, observations, progress, checkpoint, description, start=None,
                        kind: str = "process") -> SmootherResult:
        """Type-II maximum likelihood of one factor on Q (``kind="process"``) or on R
        (``"measurement"``): ``process_noise`` and ``measurement_noise`` in the class docstring."""
        check_model(model)
        y = check_observations(model, observations)
        kmin = math.ceil(math.log(self.noise_range[0], 4.0) - 1e-9)
        kmax = math.floor(math.log(self.noise_range[1], 4.0) + 1e-9)
        inner = replace(self, process_noise="fixed", measurement_noise="fixed", covariance=False)
        scaled_noise, symbol, tag = ((scaled_process_noise, "Q", "noise") if kind == "process"
                                     else (scaled_measurement_noise, "R", "Rnoise"))
        fits, evidence, caught = {}, {}, {}
        bar = None
        if progress:
            from tqdm import tqdm
            bar = tqdm(desc=f"{description}: {kind} noise level", unit="scale", leave=False)

        def at(k, start):
            cp = None if checkpoint is None else f"{checkpoint}.{tag}{k:+.4f}"
            # a trial level's warnings are kept, and only the chosen level's are shown (below); a level
            # that fails shows its own before the error goes on
            try:
                with warnings.catch_warnings(record=True) as caught[k]:
                    warnings.simplefilter("always")
                    fits[k] = inner._fit(scaled_noise(model, 4.0 ** k), y, progress=progress, checkpoint=cp,
                                         description=f"{description} ({symbol} x {4.0 ** k:.3g})", start=start)
            except BaseException:
                _reemit(caught.get(k, ()), f"({description}, at the {kind} noise level tried when it stopped: "
                                           f"{symbol} x {4.0 ** k:.3g})")
                raise
            evidence[k] = fits[k].log_likelihood
            if bar is not None:
                bar.update(1)
                bar.set_postfix(scale=f"{4.0 ** k:.3g}", log_evidence=f"{evidence[k]:.2f}")
            return evidence[k]

        try:
            at(0.0, start)
            for direction in (-1.0, 1.0):
                k = 0.0
                while kmin <= k + direction <= kmax:
                    at(k + direction, fits[k].states)
                    if not evidence[k + direction] > evidence[k] + self.noise_tol:
                        break
                    k += direction
                if k != 0.0:
                    break                       # the evidence rose downwards: no need to look up
            best = max(evidence, key=evidence.get)
            if best - 1.0 in evidence and best + 1.0 in evidence:
                lo, mid, hi = evidence[best - 1.0], evidence[best], evidence[best + 1.0]
                curvature = hi - 2.0 * mid + lo
                if curvature < 0.0:
                    vertex = best - 0.5 * (hi - lo) / curvature
                    if abs(vertex - best) > 0.05:
                        at(vertex, fits[best].states)
                        best = max(evidence, key=evidence.get)
        finally:
            if bar is not None:
                bar.close()
        _reemit(caught.get(best, ()), f"({description}, at the {kind} noise level chosen: {symbol} x "
                                      f"{4.0 ** best:.3g})")
        # the walk stopped at an end of the range while the evidence still rose by more than noise_tol
        inward = best - 1.0 if best == kmax else best + 1.0
        edge = best in (kmin, kmax) and inward in evidence and evidence[best] > evidence[inward] + self.noise_tol
        if edge and best != 0.0:
            warnings.warn(f"{description}: the evidence for the {kind} noise level is highest at the end of "
                          f"noise_range ({symbol} x {4.0 ** best:.3g}; range {self.noise_range[0]:.3g} to "
                          f"{self.noise_range[1]:.3g}): the level may lie beyond it; widen noise_range",
                          RuntimeWarning, stacklevel=4)      # run (through its BLAS-threads decorator)
        scale = 4.0 ** best
        chosen, scaled = fits[best], scaled_noise(model, scale)
        guard = self.safeguards if self.safeguards is not None else Safeguards()
        result = laplace_at_mode(scaled, y, chosen.states, chosen.cost, chosen.records, chosen.stop_reason,
                                 chosen.converged, guard, covariance=self.covariance) if self.covariance else chosen
        search = [{"scale": 4.0 ** k, "log_evidence": float(evidence[k]),
                   "iterations": int(fits[k].iterations), "converged": bool(fits[k].converged)}
                  for k in sorted(evidence)]
        if kind == "process":
            result.process_noise_scale, result.noise_search = scale, search
        else:
            result.measurement_noise_scale, result.measurement_noise_search = scale, search
        return result

    def _fit(self, model, observations, *, progress: bool = False, checkpoint=None,
             description: str = "iterated smoother", start=None) -> SmootherResult:
        """One run at the model's Q (:func:`~sfem_filters.filtering.gauss_newton.gauss_newton_fit`);
        ``start``: a trajectory (n_frames, dim_state) whose material is the first iterate instead
        of the prior mean."""
        return gauss_newton_fit(self, model, observations, progress=progress, checkpoint=checkpoint,
                                description=description, start=start)


def _reemit(records, note: str) -> None:
    """Show recorded warnings again, each with ``note`` after its text, as from the place that first
    warned (its module too, so that a filter by module still applies)."""
    modules = {getattr(m, "__file__", None): name for name, m in list(sys.modules.items())}
    for w in records:
        warnings.warn_explicit(f"{w.message} {note}", w.category, w.filename, w.lineno,
                               module=modules.get(w.filename, __name__), source=w.source)


def iterated_smoother(model, observations, *, progress: bool = False, checkpoint=None,
                      description: str = "iterated smoother", **settings) -> SmootherResult:
    """``IteratedSmoother(**settings).run(model, observations, ...)``; see :class:`IteratedSmoother`."""
    return IteratedSmoother(**settings).run(model, observations, progress=progress, checkpoint=checkpoint,
                                            description=description)
