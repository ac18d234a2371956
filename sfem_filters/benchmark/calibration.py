"""Is a reported uncertainty honest? Simulation-based calibration of the material posterior.

Follows ``shared/specs/calibration.md``: over replicates whose true material is drawn from the
prior, a calibrated posterior puts the truth inside its 95% intervals 95% of the time and its
normalised estimation error squared (NEES) averages to the number of parameters p. Two problems:

* ``"pinned"``: the spec's check. The pinned benchmark's geometry, loads, noise and filter
  configuration with a 2-region map (middle part / rest, p = 4); replicate i draws theta with
  ``default_rng(1000 + i)``, simulates the noise-free trajectory of that material by the exact
  discretisation and adds 0.1 mm noise from the same generator.
* ``"pinned_process_noise"``: the same, but the truth moves with the process noise the filter
  configuration assumes (Q of the pinned joint EKF, drawn after the measurement noise from the
  same generator): the spec's truth has none, so there an exact posterior of the filter's model
  is conservative; here the model is right. Ours, beyond the spec.
* ``"annulus"``: a 12-region relative map (p = 23) on the synthetic annulus of
  :func:`sfem_filters.cardiac.annulus.annulus_sequence`, whose motion follows the measured-data
  model exactly (penalty drive, elastically correlated process noise, measurement noise) with
  the drawn material; the estimator's model is that generator's. Here the true strain is known
  too, so the smoothed strain intervals are checked as well.

Estimators (:data:`ESTIMATORS`): the paper's cyclic EKF with its carried covariance
(``"cyclic_ekf"``), the same run with the covariance of one cycle
(``"cyclic_ekf_one_cycle"``, :func:`sfem_filters.filtering.cyclic.one_cycle_covariance`), and
the iterated smoother's Laplace posterior (``"iterated_smoother"``), the same with the process
noise level estimated from the data by maximum evidence (``"smoother_estimated_q"``,
``IteratedSmoother(process_noise="estimate")``), and Moireau & Chapelle's
reduced-order UKF in the same cyclic driver (``"roukf"``, ``"roukf_one_cycle"``;
:mod:`sfem_filters.filtering.roukf`).

>>> from sfem_filters.benchmark.calibration import pinned_problem
>>> model, y, theta_true, _ = pinned_problem(0)
>>> model.dim_theta, y.shape
(4, (16, 26))
"""
from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sla
from scipy import stats

from .._validate import integer
from ..cardiac import measured
from ..cardiac.annulus import annulus_sequence
from ..fem.material import Parameterisation
from ..fem.strain import nodal_strains
from ..filtering.cyclic import CyclicEKF
from ..filtering.diagnostics import prior_conflict
from ..filtering.protocol import parameter_prior
from ..filtering.iterated import IteratedSmoother
from .pinned import benchmark_model, pinned_benchmark
from .statistics import wilson_interval

__all__ = ["ESTIMATORS", "PROBLEMS", "Replicate", "Calibration", "pinned_problem", "annulus_problem", "calibrate",
           "format_calibration", "wilson_interval"]

#: Estimators compared, by name.
ESTIMATORS = ("cyclic_ekf", "cyclic_ekf_one_cycle", "iterated_smoother", "smoother_estimated_q", "roukf",
              "roukf_one_cycle")
#: Calibration problems, by name.
PROBLEMS = ("pinned", "pinned_process_noise", "annulus")


def pinned_problem(i: int, noise_mm: float = 0.1, process_noise: bool = False):
    """Replicate ``i`` of the spec's check: ``(model, observations, theta_true, truth)``.

    ``truth`` is None (the spec checks the material only). ``process_noise``: the truth also
    moves with the filter configuration's process noise (``"pinned_process_noise"``).
    """
    i = integer("i", i, 0)
    bench = _pinned_base()
    model = benchmark_model(bench, "joint_ekf", parameterisation=Parameterisation.per_region(bench.middle))
    nr = model.n_restart
    rng = np.random.default_rng(1000 + i)
    L = np.linalg.cholesky(model.P0[nr:, nr:])
    theta_true = model.x0[nr:] + L @ rng.standard_normal(model.dim_theta)
    system = model.system(theta_true)
    w = model.dofmap.restrict(model.loads)
    D = model.observation_operator
    noise = noise_mm * 1e-3 * rng.standard_normal((model.n_frames, D.shape[0]))
    Lq = np.linalg.cholesky(model.Q[:model.dim_x, :model.dim_x]) if process_noise else None
    x = np.zeros(model.dim_x)
    U = [model.displacements(x)]
    for t in range(1, model.n_frames):
        x = system.step(x, w[t])
        if Lq is not None:
            x = x + Lq @ rng.standard_normal(model.dim_x)
        U.append(model.displacements(x))
    y = (D @ np.array(U).T).T + noise
    return model, y, theta_true, None


_PINNED = {}


def _pinned_base():
    if "bench" not in _PINNED:
        _PINNED["bench"] = pinned_benchmark(0)
    return _PINNED["bench"]


def annulus_problem(i: int, n_frames: int = 24, landmarks: int = 8, noise_px: float = 0.05,
                    landmark_step_px: float = 0.15):
    """Replicate ``i`` on the synthetic annulus: ``(model, observations, theta_true, truth)``.

    theta (relative E of 12 regions, nu of each) is drawn from the region model's prior with
    ``default_rng([1000 + i, 1])``; the sequence is generated with seed ``1000 + i``.
    ``truth`` holds the mesh and the true nodal strains ``(n_frames, n_nodes, 3)``.
    """
    i = integer("i", i, 0)
    stub = annulus_sequence(None, n_frames=3, seed=0)
    setup0 = measured.prepare(stub, landmarks)
    setup0.noise_px = noise_px
    prior_model, _ = measured.build_model(setup0, (), "penalty", "region", landmark_step_px=landmark_step_px)
    nr = prior_model.n_restart
    rng = np.random.default_rng([1000 + i, 1])
    L = np.linalg.cholesky(prior_model.P0[nr:, nr:])
    theta_true = prior_model.x0[nr:] + L @ rng.standard_normal(prior_model.dim_theta)
    material = prior_model.parameterisation.material(theta_true)
    seq, truth = annulus_sequence(None, seed=1000 + i, n_frames=n_frames, noise_px=noise_px,
                                  landmark_step_px=landmark_step_px, landmarks=landmarks, return_truth=True,
                                  material=material)
    setup = measured.prepare(seq, landmarks)
    setup.noise_px = noise_px
    model, y = measured.build_model(setup, (), "penalty", "region", landmark_step_px=landmark_step_px)
    U = truth["displacement"].reshape(n_frames, -1) * setup.spacing
    return model, y, theta_true, {"mesh": setup.mesh, "strain": nodal_strains(setup.mesh, U)}


@dataclass
class Replicate:
    """One replicate's estimate against its truth."""

    index: int
    theta_true: np.ndarray
    theta_hat: np.ndarray
    P_theta: np.ndarray
    converged: bool
    seconds: float
    strain_inside: float = np.nan     # fraction of (frame, node, component) strains inside their 95% interval
    process_noise_scale: float = 1.0  # factor on the model's Q the estimate used
    prior_check: dict | None = None   # the prior-data check (chi2, dof, flagged) of the estimate, if computed

    @property
    def nees(self) -> float:
        """Normalised estimation error squared ``d^T P_theta^-1 d``, ``d = theta_hat - theta_true``
        (distributed as chi2(p) for a calibrated posterior)."""
        d = self.theta_hat - self.theta_true
        return float(d @ sla.cho_solve(sla.cho_factor(self.P_theta), d))

    @property
    def inside(self) -> np.ndarray:
        """(p,) bool: whether each parameter's truth lies in its 95% interval ``theta_hat +- 1.96 sd``."""
        return np.abs(self.theta_hat - self.theta_true) <= 1.96 * np.sqrt(np.diag(self.P_theta))


@dataclass
class Calibration:
    """The replicates of one estimator on one problem, and their summary."""

    problem: str
    estimator: str
    replicates: list = field(default_factory=list)

    @property
    def n(self) -> int:
        """Number of replicates N."""
        return len(self.replicates)

    @property
    def p(self) -> int:
        """Number of parameters p (the length of theta)."""
        return len(self.replicates[0].theta_true)

    @property
    def anees_over_p(self) -> float:
        """Mean NEES over the replicates divided by p: 1 for a calibrated posterior (see :attr:`anees_band`)."""
        return float(np.mean([r.nees for r in self.replicates]) / self.p)

    @property
    def anees_band(self) -> tuple:
        """The 95% band of ANEES / p for a calibrated posterior: chi2(0.025 / 0.975, N p) / (N p)."""
        k = self.n * self.p
        return float(stats.chi2.ppf(0.025, k) / k), float(stats.chi2.ppf(0.975, k) / k)

    @property
    def coverage(self) -> float:
        """Fraction of (replicate, parameter) pairs whose truth lies in its 95% interval: 0.95 when calibrated."""
        return float(np.mean([r.inside for r in self.replicates]))

    @property
    def coverage_interval(self) -> tuple:
        """95% Wilson interval ``(low, high)`` of :attr:`coverage` over the N p (replicate, parameter) pairs."""
        inside = np.concatenate([r.inside for r in self.replicates])
        return wilson_interval(int(inside.sum()), len(inside))

    @property
    def strain_coverage(self) -> float:
        """Mean over the replicates of the fraction of true strains inside their 95% interval (0.95 when
        calibrated); NaN when no replicate's strain was checked (only the annulus problem checks it)."""
        vals = [r.strain_inside for r in self.replicates if np.isfinite(r.strain_inside)]
        return float(np.mean(vals)) if vals else np.nan

    def summary(self) -> dict:
        """The calibration's numbers as plain values (one row of the report).

        Returns
        -------
        dict
            ``problem``, ``estimator``, ``n``, ``p``, ``anees_over_p`` and its calibrated ``anees_band``,
            ``coverage`` and its ``coverage_interval``, ``strain_coverage``, the number of ``converged``
            replicates, the medians ``process_noise_scale_median`` and ``seconds_median`` (s), and the
            prior-data check's keys (:meth:`prior_check_summary`).
        """
        lo, hi = self.anees_band
        clo, chi = self.coverage_interval
        return {"problem": self.problem, "estimator": self.estimator, "n": self.n, "p": self.p,
                "anees_over_p": self.anees_over_p, "anees_band": [lo, hi], "coverage": self.coverage,
                "coverage_interval": [clo, chi], "strain_coverage": self.strain_coverage,
                "converged": int(sum(r.converged for r in self.replicates)),
                "process_noise_scale_median": float(np.median([r.process_noise_scale for r in self.replicates])),
                "seconds_median": float(np.median([r.seconds for r in self.replicates])),
                **self.prior_check_summary()}

    def prior_check_summary(self) -> dict:
        """The prior-data check over the replicates (:func:`sfem_filters.filtering.diagnostics.prior_conflict`,
        family-wise level 0.99): its pooled chi-square over its pooled dof (1 when calibrated) and the
        fraction of replicates with a flagged parameter (at most about 1% when calibrated; the truth
        is drawn from the prior, so there is no conflict to find)."""
        checks = [r.prior_check for r in self.replicates if r.prior_check is not None]
        if not checks:
            return {"prior_check_chi2_over_dof": np.nan, "prior_check_flagged": np.nan}
        dof = sum(c["dof"] for c in checks)
        return {"prior_check_chi2_over_dof": float(sum(c["chi2"] for c in checks) / dof) if dof else np.nan,
                "prior_check_flagged": float(np.mean([c["flagged"] > 0 for c in checks]))}


def _strain_inside(model, result, truth) -> float:
    if truth is None or "strain" not in result.output_sd:
        return np.nan
    est = nodal_strains(truth["mesh"], model.displacements(result.states))
    sd = result.output_sd["strain"].reshape(est.shape)
    return float(np.mean(np.abs(est - truth["strain"]) <= 1.96 * sd))


def calibrate(problem: str = "pinned", estimators=ESTIMATORS, n: int = 200, start: int = 0,
              progress: bool = False) -> dict:
    """Run ``n`` replicates (indices ``start .. start + n - 1``) of ``problem`` with each estimator.

    Returns ``{estimator: Calibration}``. The two cyclic EKF estimators share one run per
    replicate, as do the two reduced-order UKF ones.
    """
    if problem not in PROBLEMS:
        raise ValueError(f"problem: expected one of {PROBLEMS}, got {problem!r}")
    estimators = tuple(estimators)
    unknown = set(estimators) - set(ESTIMATORS)
    if unknown:
        raise ValueError(f"estimators: expected names from {ESTIMATORS}, got {sorted(unknown)}")
    integer("n", n, 1)
    integer("start", start, 0)
    make = {"pinned": pinned_problem, "annulus": annulus_problem,
            "pinned_process_noise": lambda i: pinned_problem(i, process_noise=True)}[problem]
    out = {e: Calibration(problem, e) for e in estimators}
    indices = range(start, start + n)
    if progress:
        from tqdm import tqdm
        indices = tqdm(indices, desc=f"calibration {problem}", unit="replicate", leave=False)
    def check(model, theta, P):
        c = prior_conflict(theta, P, *parameter_prior(model))
        return {"chi2": c["chi2"], "dof": c["dof"], "flagged": len(c["flagged"])}

    for i in indices:
        model, y, theta_true, truth = make(i)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            if {"cyclic_ekf", "cyclic_ekf_one_cycle"} & set(estimators):
                t0 = time.perf_counter()
                res = CyclicEKF().run(model, y)
                sec = time.perf_counter() - t0
                for name, P in (("cyclic_ekf", res.P_theta), ("cyclic_ekf_one_cycle", res.P_theta_one_cycle)):
                    if name in out:
                        out[name].replicates.append(Replicate(i, theta_true, res.theta, P, res.converged, sec,
                                                              prior_check=check(model, res.theta, P)))
            if {"roukf", "roukf_one_cycle"} & set(estimators):
                t0 = time.perf_counter()
                res = CyclicEKF(engine="roukf").run(model, y)
                sec = time.perf_counter() - t0
                for name, P in (("roukf", res.P_theta), ("roukf_one_cycle", res.P_theta_one_cycle)):
                    if name in out:
                        out[name].replicates.append(Replicate(i, theta_true, res.theta, P, res.converged, sec,
                                                              prior_check=check(model, res.theta, P)))
            for name, noise in (("iterated_smoother", "fixed"), ("smoother_estimated_q", "estimate")):
                if name in estimators:
                    t0 = time.perf_counter()
                    res = IteratedSmoother(process_noise=noise).run(model, y)
                    out[name].replicates.append(
                        Replicate(i, theta_true, res.theta, res.P_theta, res.converged, time.perf_counter() - t0,
                                  _strain_inside(model, res, truth), res.process_noise_scale,
                                  check(model, res.theta, res.P_theta)))
    return out


def format_calibration(results) -> str:
    """Text table: ANEES / p with its band, coverage of the 95% intervals with its Wilson interval
    (and, when an estimator estimated the process noise level, the median factor on Q)."""
    rows = [c.summary() for c in (results.values() if isinstance(results, dict) else results)]
    scaled = any(r["estimator"].endswith("estimated_q") for r in rows)
    lines = [f"{'problem':<22}{'estimator':<22}{'N':>5}{'p':>4}{'ANEES/p':>9}{'95% band':>14}{'coverage':>10}"
             f"{'Wilson 95%':>15}{'strain cov.':>12}{'converged':>10}{'s/run':>8}" + (f"{'Q x, median':>13}" if scaled else "")]
    for r in rows:
        band = f"{r['anees_band'][0]:.2f}-{r['anees_band'][1]:.2f}"
        wil = f"{r['coverage_interval'][0]:.3f}-{r['coverage_interval'][1]:.3f}"
        sc = "" if not np.isfinite(r["strain_coverage"]) else f"{r['strain_coverage']:.3f}"
        lines.append(f"{r['problem']:<22}{r['estimator']:<22}{r['n']:>5}{r['p']:>4}{r['anees_over_p']:>9.3f}{band:>14}"
                     f"{r['coverage']:>10.3f}{wil:>15}{sc:>12}{r['converged']:>6}/{r['n']:<3}{r['seconds_median']:>8.2f}"
                     + (f"{r['process_noise_scale_median']:>13.3g}" if scaled else ""))
    checked = [r for r in rows if np.isfinite(r.get("prior_check_chi2_over_dof", np.nan))]
    if checked:
        lines.append(f"prior-data check of the estimates (diagnostics.prior_conflict; calibrated: chi2/dof 1, "
                     f"at most ~1% of replicates flagged at the family-wise 1% level):")
        for r in checked:
            lines.append(f"  {r['problem']:<22}{r['estimator']:<22} chi2/dof {r['prior_check_chi2_over_dof']:>6.3f}"
                         f"   flagged {100 * r['prior_check_flagged']:>5.1f}%")
    return "\n".join(lines)
