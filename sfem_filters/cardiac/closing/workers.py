"""The rounds' fits: one fit of a model (:func:`_fit`), and a round's fits one after the other or
side by side in worker processes (:class:`_Fits`, :func:`fit_workers`)."""
from __future__ import annotations

import warnings
from concurrent.futures.process import BrokenProcessPool
from dataclasses import replace

from tqdm.auto import tqdm

from ..._validate import integer
from ...filtering.smoother import PEAK_FACTOR, WORKING
from ...resources import available_memory, blas_threads, frame_threads, process_pool, starting_workers, usable_cores
from ..measured import Run, run
from ..specs import EstimatorSettings, ModelSpec
from .criteria import round_cross_validation
from .progress import progress_line

__all__ = ["fit_workers", "usable_cores"]


def _fit(setup, spec: ModelSpec, estimator: EstimatorSettings, *, progress: bool = False,
         description: str | None = None, covariance: bool = True, warm_start=None,
         max_iterations: int | None = None, threads: int = 1) -> Run:
    """One fit of the model ``spec`` with ``estimator`` (its ``max_iterations`` resolved);
    ``description`` names it on its progress bar (``"baseline (region map)"``, ``"round 2: +
    active_polar"``; default the spec's label), and the run's name is the spec's label.
    ``covariance``, ``warm_start``: :func:`~sfem_filters.cardiac.measured.run`'s; ``max_iterations``:
    a limit below the estimator's (a screening fit); ``threads``: each linearisation's frames on this
    many threads (:class:`~sfem_filters.resources.frame_threads`: the same figures, sooner where
    cores idle)."""
    name = spec.label(spec.drive)
    # one BLAS thread per fit, whether the fits run one after the other or side by side: the
    # threads' order of summation is then the same, and so is every figure (measured: a second
    # BLAS thread does not make a fit of the shipped slice faster, benchmarks/blas_threads.py).
    # A screening fit stops after a few iterations, far from its mode: its filter's consistency
    # warnings say nothing of the model (the fit kept is refitted to the full limit, and warns then)
    with blas_threads(1), frame_threads(threads), warnings.catch_warnings():
        if max_iterations is not None:
            warnings.filterwarnings("ignore", message="filter inconsistent")
        out = run(setup, spec.effects, spec.drive, parameterisation=spec.material_map, name=description or name,
                  effect_rates=spec.effect_rates, drive_trend=spec.drive_trend, process_scale=spec.process_scale,
                  spring_scale=spec.spring_scale, estimator=estimator.estimator, max_loops=estimator.max_loops,
                  max_iterations=estimator.max_iterations if max_iterations is None else max_iterations,
                  measurement_noise=estimator.measurement_noise, progress=progress, covariance=covariance,
                  warm_start=warm_start)
    return replace(out, name=name) if isinstance(out, Run) else out


def _fit_job(setup, spec: ModelSpec, estimator: EstimatorSettings, cv_folds, **how) -> tuple:
    """One fit of the rounds (``how``: :func:`_fit`'s keywords) and, when the criterion is
    cross-validation, its cross-validation: ``(run, cv or None)``. Module level, so that a worker
    process can run it."""
    trial = _fit(setup, spec, estimator, **how)
    return trial, (round_cross_validation(setup, spec, trial, cv_folds) if cv_folds else None)


def fit_workers(workers, n_state: int, n_frames: int, available: float | None = None) -> int:
    """How many fits of the rounds run side by side (:func:`closing_the_loop` ``workers``).

    ``None`` (automatic): one per usable core (:func:`usable_cores`), but no more than the
    available memory holds at a conservative estimate of a fit's peak beside the fit this process
    has just made: :data:`~sfem_filters.filtering.smoother.PEAK_FACTOR` times what a covariance
    pass keeping every frame's covariance holds (``n_frames`` n_state x n_state covariances and
    :data:`~sfem_filters.filtering.smoother.WORKING` more, 8 bytes a float), although the rounds'
    fits keep no covariance at all; at least 1. An integer >= 1 is taken as given.
    """
    if workers is not None:
        return integer("workers", workers, 1)
    n = usable_cores()
    available = available_memory() if available is None else float(available)
    if available is not None:
        peak = PEAK_FACTOR * 8.0 * (n_frames + WORKING) * float(n_state) ** 2
        n = min(n, int(available // peak) if peak > 0 else n)
    return max(n, 1)


class _Fits:
    """The rounds' fits, one after the other (``workers=1``) or side by side in worker processes.

    Results are used in the order the serial search would make them, so the rounds take the same
    path either way; with several workers a batch of fits whose outcome is not needed (after the
    first accepted one, ``selection="first"``) may have run for nothing.
    """

    def __init__(self, setup, estimator: EstimatorSettings, workers: int, cv_folds, progress: bool,
                 warm_start: bool = False, threads: int = 1):
        smoother = estimator.estimator == "smoother"
        # most fits are tried and let go: the smoother makes the variances of their kinematics and
        # strains only for those kept (kept(), measured.with_covariance: the same figures)
        self.setup, self.estimator, self.covariance = setup, estimator, not smoother
        self.workers, self.cv_folds = workers, cv_folds
        # the fits made here (one at a time, while the workers wait) take their frames on these threads
        self.threads = int(threads)
        self.progress, self.warm_start = progress, bool(warm_start) and smoother
        self.pool = None
        if workers > 1:
            try:
                self.pool = process_pool(workers)           # started afresh: no copy of this process's BLAS threads
            except (OSError, ImportError) as exc:           # no process semaphores here (some sandboxes)
                self._serial(exc)

    def _serial(self, exc) -> None:
        warnings.warn(f"closing_the_loop: the fits run one after the other instead of in {self.workers} worker "
                      f"processes ({type(exc).__name__}: {exc})", RuntimeWarning, stacklevel=4)
        if self.pool is not None:
            self.pool.shutdown(wait=False, cancel_futures=True)
        self.pool = None

    def run(self, variants, label: str = "fits", names=None, warm=None, iterations: int | None = None):
        """Yield ``(run, cv)`` for each variant, in the given order. A pool that cannot start or
        breaks (a worker killed, for example for memory) is a warning, and the fits not yet
        returned are made here; an error of a fit itself is raised as it is. ``names`` (one per
        variant, optional) name the fits made here on their progress bars, after ``label``.
        ``warm``: the run whose material mode the fits start from (with ``warm_start``; a fit of
        another parameterisation starts from the prior mean); ``iterations``: at most this many
        Gauss-Newton iterations instead of the rounds' limit (a screening fit)."""
        variants = list(variants)
        how = {"covariance": self.covariance,
               "warm_start": warm.result.theta if self.warm_start and warm is not None else None,
               "max_iterations": None if iterations is None else
               min(int(iterations), int(self.estimator.max_iterations or iterations))}
        names = [v.label(v.drive) if isinstance(v, ModelSpec) else str(v) for v in variants] if names is None \
            else list(names)
        done = 0
        if self.pool is not None and len(variants) > 1:
            progress_line(f"{label}: fitting {len(variants)} models side by side in {self.workers} worker processes "
                          f"({', '.join(names)})", self.progress)
            bar = tqdm(total=len(variants), desc=f"{label} ({self.workers} workers)", unit="fit",
                       disable=not self.progress, leave=False)
            futures = []
            try:
                with starting_workers():                # the workers start with Ctrl-C ignored: abort() stops them
                    # one bar for a batch of fits, not one per worker
                    futures = [self.pool.submit(_fit_job, self.setup, v, self.estimator, self.cv_folds, progress=False,
                                                **how) for v in variants]
                for i, f in enumerate(futures):
                    out = f.result()
                    futures[i] = None                       # a fit is held once, by whoever takes it
                    bar.update(1)
                    done += 1
                    yield out
            except (BrokenProcessPool, OSError) as exc:
                self._serial(exc)
            finally:
                bar.close()
                for f in futures:
                    if f is not None:
                        f.cancel()
        for v, name in zip(variants[done:], names[done:]):
            yield _fit_job(self.setup, v, self.estimator, self.cv_folds, progress=self.progress,
                           description=f"{label}: {name}", threads=self.threads, **how)

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(wait=True, cancel_futures=True)

    def abort(self) -> None:
        """Stop at once (Ctrl-C): cancel the fits not started, terminate the workers and shut the
        pool down, so that its queues and semaphores are released (no leaked semaphores)."""
        pool, self.pool = self.pool, None
        if pool is None:
            return
        workers = list((getattr(pool, "_processes", None) or {}).values())
        for w in workers:
            if w.is_alive():
                w.terminate()
        pool.shutdown(wait=True, cancel_futures=True)
        for w in workers:
            w.join(timeout=5.0)
