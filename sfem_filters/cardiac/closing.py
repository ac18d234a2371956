"""Closing the loop on measured data: residual diagnosis, missing effects added round by round.

Step 5 of the paper's section 3.2 workflow, on top of :mod:`sfem_filters.cardiac.measured`,
repeated until the data stop asking for more. Each round scores every remaining candidate of
the catalogue (:mod:`sfem_filters.cardiac.effects`) on the current model's innovations (a score
test per candidate, :func:`sfem_filters.filtering.diagnostics.rank_effects`) and adds the best
one only if

(a) its score is significant after a Bonferroni correction for every score test made so far
    (``-log10 p > -log10(alpha / m)``, m counted over all rounds), and
(b) the model's evidence ``log p(y)`` from the observed data alone rises by more than
    ``min_evidence`` nats (:func:`log_evidence`: the Laplace approximation of the marginal
    likelihood, which the iterated smoother's final pass gives by the prediction-error
    decomposition).

The evidence is the default criterion because it carries its own Occam penalty: an effect's
amplitudes are random walks with a prior, integrated out, so a term that does not explain the
data lowers ``log p(y)`` (Laplace's approximation is the origin of BIC, without BIC's count of
"free parameters" that random-walk states do not have). It scores the one-frame-ahead prediction
of the observed points, not the interpolation between them that held-out points measure; with
``criterion="cv"`` (b) is instead a fall of the K-fold cross-validation error over the observed
points by more than ``min_cv_gain`` of it (:mod:`sfem_filters.cardiac.crossval`: each fold's
points neither drive nor are observed, and are predicted by the smoothed kinematics of the
rest). Every round's model is cross-validated either way, beside the spline's cross-validation
on the same folds, so a report shows both criteria. By default (``selection="best"``) the
significant candidates (at most ``max_tries``, by score) are all fitted and the one that improves
the criterion most is kept: where candidates overlap (six segments and a smooth harmonic field both
explain a regional stress) the score test's order, which favours the candidate with fewer free
amplitudes per frame, does not decide which of them enters. With ``selection="first"`` a
significant candidate that fails (b) is set aside and the next significant one is fitted (at most
``max_tries`` fits per round), and the first that passes is kept.

Once the model has effects, every candidate gets two score tests, both counted in m: one with a
free amplitude in every frame, and one with its amplitudes tied to a constant and the current
effects' estimated time courses (:func:`time_courses`). A refinement of an effect already in the
model (one wall segment that does not contract, a fibre direction turning through the wall)
moves with that effect, and the tied test asks a few coefficients per amplitude where the free
test spends one per frame (12 per frame for the six segments on 16 landmarks), so it finds such
a refinement where the free test cannot. The baseline, with no time course to tie to, gets the
free test only.

When no effect passes, corrections of the model's own drive and priors are the candidates,
each only when the residual points to it (:func:`_corrections`): springs on the whole contour,
the landmarks' motion interpolated along it, instead of on the isolated landmarks, whose pull
forms tents in the wall between them; springs ten times stiffer; when the
innovations are correlated in time, spring targets extrapolated from the last two frames
instead of held a frame behind, and effect amplitudes that follow a trend; when the NIS is off
its expected value from above, the process noise doubled; and a smoother prior of the material
(independent regions or elements replaced by the smooth basis of a few modes): a map of
independent regions can absorb a misfit of the border in the stiffness of the regions under it,
which a smooth field cannot. They have no score test (the drive's direction changes with each
frame's data): all that apply are fitted, and the one that raises the criterion most is kept.

After every round that adds a term, the rounds also step backward (``prune=True``, the default;
:func:`removals`): each earlier term (an effect, or a correction of the drive, the noise or the material) is
taken out in turn, an effect is also tried replaced by an effect it strictly contains (the six
segments by the uniform stress), and the change that improves the criterion most is made, as long
as one does. A greedy forward search can let a term enter that a later one makes unnecessary:
stiffer springs that stand in for a missing effect until the effect becomes significant, or the
segments where the uniform stress suffices once a transmural effect is in. Every step, forward or
backward, raises the criterion strictly, and a model fitted once is not fitted again, so the
search cannot cycle; it is stepwise selection in both directions (Efroymson 1960).

Candidates that explain the same thing are kept from piling up in three ways: the ranking is
redone on the extended model's innovations, so what the added effect explains no longer counts
for the others (``cavity_pressure`` after ``active_polar`` on a circular wall); a candidate whose
loads lie in the span of the current effects' loads is not scored (it can explain nothing new);
and a candidate whose span contains a current effect replaces it instead of joining it
(``active_segments`` contains ``active_polar``: six segments with equal amplitudes are the
uniform effect), so the model never carries two unidentifiable copies of one cause. With a
measured pressure the stiffness level is a parameter of the material (see
:func:`sfem_filters.cardiac.measured.build_model`), so a scale error is not left for
``cavity_pressure`` to absorb.

Every report carries the physics-free yardstick (:func:`sfem_filters.cardiac.reference.spline_reference`):
a thin-plate spline through the same observed points, scored on the same held-out points; and
for every round the model plus the same spline of the model's own residual at the observed
points (:func:`sfem_filters.cardiac.reference.residual_spline`), held out and cross-validated:
below the spline's error only where the physics captures what interpolation misses. Both
differences from the spline come with a 95% interval (:func:`versus_spline`: a jackknife over
angular sectors of the held-out points, whose errors are alike within a gap between landmarks),
so that a report says whether a difference is more than the luck of which points were held out.
:func:`closing_the_loop` returns all rounds as a :class:`LoopResult`.

Most fits of the rounds are tried and let go, so they are made without the smoothed variances
of their kinematics and strains (the covariance recursion of the smoother's final pass, its
dearest part), and a fit that is kept gets them afterwards
(:func:`sfem_filters.cardiac.measured.with_covariance`): the same figures, bit for bit.
The fits of a round (its significant candidates, its corrections, its backward steps) do not
depend on each other, so ``workers=N`` makes them side by side in N processes
(:func:`fit_workers`; ``sfem-filters dense`` uses one per core). Every fit runs on one BLAS thread
either way, and the search reads the fits in the order it would have made them, so the rounds
take the same path and the report has the same figures whatever N (tested bit for bit). Workers
are started afresh (``spawn``), so a script that passes ``workers > 1`` needs the usual
``if __name__ == "__main__":`` guard.
"""
from __future__ import annotations

import re
import sys
import time
import warnings
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace

import numpy as np
from tqdm.auto import tqdm

from .._validate import integer, non_negative, probability
from ..filtering import diagnostics
from ..filtering.iterated import NOISE_LEVELS
from ..filtering.smoother import PEAK_FACTOR, WORKING
from ..resources import available_memory, blas_threads, process_pool, starting_workers, usable_cores
from .crossval import DEFAULT_FOLDS, cross_validate, observation_folds, spline_cross_validation
from .effects import CATALOGUE, EXPLICIT_ONLY, build_effects
from .measured import (ELEMENT_PX, NOMINAL, Run, Setup, angle_from_origin, default_max_iterations,
                       equivalent_eigenstrain, exact_posterior, kriged_heldout, measured_wall_kinematics, prepare, run, with_covariance)
from .reference import angular_sectors, rmse_difference, spline_reference
from .sequence import Sequence

__all__ = ["LoopResult", "Round", "Variant", "closing_the_loop", "candidate_loads", "spans", "log_evidence", "format_report",
           "removals", "fit_workers", "usable_cores",
           "versus_spline", "SELECTIONS",
           "DRIVE_CORRECTIONS", "time_courses", "CRITERIA", "round_cross_validation", "DEFAULT_CANDIDATES", "LAPLACE",
           "length_display", "not_converged_note", "progress_line", "RoundsInterrupted"]

#: How a round picks among significant candidates (``selection=``, ``--selection``): the first by
#: score that improves the criterion, or the one of the fitted that improves it most.
@dataclass(frozen=True)
class Search:
    """How thoroughly the rounds search, and on what mesh (:func:`closing_the_loop`'s settings of the
    same names; ``max_iterations`` None: :func:`~sfem_filters.cardiac.measured.default_max_iterations`
    of the drive, at least ``min_iterations``)."""

    mesh: str = "delaunay"
    element_px: float = ELEMENT_PX
    warm_start: bool = False
    screen_iterations: int | None = None
    min_iterations: int = 1

    def max_iterations(self, drive: str) -> int:
        """The smoother's iteration limit under this search for ``drive``."""
        return max(default_max_iterations(drive), self.min_iterations)

    def settings(self) -> dict:
        """The :func:`closing_the_loop` keywords of this search (beside ``max_iterations``)."""
        return {"mesh": self.mesh, "element_px": self.element_px, "warm_start": self.warm_start,
                "screen_iterations": self.screen_iterations}


#: The searches the ``dense`` command offers (``--search``). ``fast``, the default: every fit of a
#: round started from the current model's mode and screened with 3 Gauss-Newton iterations, only the
#: one kept fitted to the end, and room for the baseline to converge (40 iterations); the same path,
#: final model and held-out errors as ``full`` on the measured slice and the synthetic checks.
#: ``coarse``: the same on a mesh of the wall apart from the points (2-pixel edges), a few times
#: faster again, but another discretisation, which finds other effects on the synthetic checks
#: (drawn on the node-per-point mesh). ``full``: every fit to the end from the prior on the
#: node-per-point mesh (what the command did before the searches). The docs' validation page
#: "Closing the loop: fast and full search" measures what each finds and costs.
SEARCHES = {"fast": Search(warm_start=True, screen_iterations=3, min_iterations=40),
            "coarse": Search(mesh="polar", warm_start=True, screen_iterations=3, min_iterations=40),
            "full": Search()}

SELECTIONS = ("first", "best")

#: What decides whether a candidate is kept (``criterion=``, ``--criterion``): the evidence
#: ``log p(y)`` of the observed points, or K-fold cross-validation over them
#: (:mod:`sfem_filters.cardiac.crossval`).
CRITERIA = ("evidence", "cv")

#: The final model's material covariance (``laplace=``, ``--laplace``): the smoother's inverse
#: Gauss-Newton Hessian, or the inverse exact Hessian of the MAP cost at the mode.
LAPLACE = ("gauss-newton", "exact")

#: The candidates of the rounds when none are given: the catalogue without the effects that are
#: tried only by name (:data:`~sfem_filters.cardiac.effects.EXPLICIT_ONLY`).
DEFAULT_CANDIDATES = tuple(sorted(n for n in CATALOGUE if n not in EXPLICIT_ONLY))

_SPAN_TOL = 1e-6


def candidate_loads(setup: Setup, names=None) -> list:
    """(name, load matrix) of the named catalogue effects (default :data:`DEFAULT_CANDIDATES`), for scoring."""
    names = DEFAULT_CANDIDATES if names is None else names
    effs = build_effects(names, setup.mesh, setup.geometry, angle_origin_deg=setup.angle_origin_deg,
                         scale=NOMINAL["E"])
    return [(e.name, e.loads) for e in effs]


def spans(A, B, tol: float = _SPAN_TOL) -> bool:
    """True when every column of ``B`` lies in the column span of ``A`` (relative residual of
    the least-squares fit below ``tol``): the loads ``B`` add nothing the loads ``A`` lack."""
    A, B = np.asarray(A, float), np.asarray(B, float)
    if A.size == 0:
        return not np.any(B)
    coef = np.linalg.lstsq(A, B, rcond=None)[0]
    return bool(np.linalg.norm(B - A @ coef) <= tol * max(np.linalg.norm(B), np.finfo(float).tiny))


@dataclass(frozen=True)
class Variant:
    """What a round's model is, beyond the set-up: its effects and the corrections made so far.

    Attributes
    ----------
    effects : tuple of str
        Catalogue effects (:data:`~sfem_filters.cardiac.effects.CATALOGUE`).
    drive : str
        The drive (:data:`~sfem_filters.cardiac.measured.DRIVES`).
    drive_trend : bool
        Spring targets extrapolated from the two previous frames instead of held.
    effect_rates : bool
        Effect amplitudes with rate states (integrated random walks).
    process_scale : float
        Scale of every process noise.
    spring_scale : float
        Scale of the drive's spring stiffness.
    material : str, optional
        The material map (:data:`~sfem_filters.cardiac.measured.PARAMETERISATIONS`) when the rounds
        have changed it; None: the one the rounds were configured with.
    """

    effects: tuple = ()
    drive: str = "penalty"
    drive_trend: bool = False
    effect_rates: bool = False
    process_scale: float = 1.0
    spring_scale: float = 1.0
    material: str | None = None

    def with_(self, **change) -> "Variant":
        return replace(self, **change)

    def label(self, drive: str) -> str:
        """Short text: the effects, and what differs from the configured ``drive`` and defaults."""
        out = ",".join(self.effects) or "none"
        if self.drive != drive:
            out += f" [drive {self.drive}]"
        if self.drive_trend:
            out += " [drive trend]"
        if self.effect_rates:
            out += " [effect trend]"
        if self.process_scale != 1.0:
            out += f" [noise x{self.process_scale:g}]"
        if self.spring_scale != 1.0:
            out += f" [springs x{self.spring_scale:g}]"
        if self.material is not None:
            out += f" [material {self.material}]"
        return out

    def as_json(self) -> dict:
        return {"effects": list(self.effects), "drive": self.drive, "drive_trend": self.drive_trend,
                "effect_rates": self.effect_rates, "process_scale": self.process_scale,
                "spring_scale": self.spring_scale, "material": self.material}


@dataclass(eq=False)
class Round:
    """One round of :func:`closing_the_loop`.

    Attributes
    ----------
    number : int
        0 for the baseline.
    variant : Variant
        The round's model.
    added : str or None
        The effect or correction this round added (None for the baseline and for a removal).
    replaced : tuple of str
        Effects the added one contains and replaced.
    run : Run
        The run of the round's model.
    ranking : list of dict
        Score test of every candidate on the previous round's innovations, best first
        (empty for the baseline).
    threshold : float
        The score (-log10 p) a candidate needed: ``-log10(alpha / m)``, m the score tests so far.
    tried : list of dict
        Candidates fitted in this round: effect or correction, score (None for corrections),
        evidence gain (nats), accepted.
    log_evidence : float
        The round's model's ``log p(y)`` (nats).
    cv : dict or None
        The round's model's cross-validation over the observed points
        (:func:`round_cross_validation`).
    removed : str or None
        For a backward step (:func:`removals`), the term it took out (an effect, a correction's
        name, or ``<effect>-><nested effect>``); the step shares the number of the round whose
        addition it followed.
    backward : list of dict
        The backward steps fitted from this round's model: removed term, evidence gain (nats;
        with ``criterion="cv"`` also the CV error and its fall, data units), accepted.
    """

    number: int
    variant: Variant
    added: str | None
    replaced: tuple
    run: Run
    ranking: list = field(default_factory=list)
    threshold: float = np.nan
    tried: list = field(default_factory=list)
    log_evidence: float = np.nan
    cv: dict | None = None
    removed: str | None = None
    backward: list = field(default_factory=list)

    @property
    def effects(self) -> tuple:
        return self.variant.effects

    @property
    def change(self) -> str:
        """What the round changed: ``+ <added>``, ``- <removed>``, or ``baseline``."""
        if self.removed is not None:
            return f"- {self.removed}"
        return "baseline" if self.added is None else f"+ {self.added}"

    def as_json(self) -> dict:
        m = self.run.metrics
        return {"round": self.number, **self.variant.as_json(), "added": self.added,
                "removed": self.removed, "backward": list(self.backward), "replaced": list(self.replaced), "log_evidence": self.log_evidence,
                "threshold": None if not np.isfinite(self.threshold) else float(self.threshold),
                "tried": list(self.tried), "cross_validation": self.cv,
                "ranking": _ranking_json(self.ranking),
                **{k: m[k] for k in _ROUND_KEYS}, "versus_spline": m.get("versus_spline")}


def _ranking_json(ranking) -> list:
    """A ranking's score tests as plain values."""
    keys = ("effect", "score", "lm", "df", "explained", "test", "score_per_frame", "score_time_courses")
    return [{k: r[k] for k in keys if k in r} for r in ranking]


_ROUND_KEYS = ("heldout_rmse_px", "heldout_rmse_radial_px", "heldout_rmse_circumferential_px", "residual_spline",
               "nis_mean_over_dof", "innovation_lag1_autocorrelation", "nis_z", "lag1_z",
               "shear_strain_rms_peak_model", "shear_strain_error_rms_peak", "shear_strain_correlation_peak")


@dataclass(eq=False)
class LoopResult:
    """Outcome of :func:`closing_the_loop`.

    Attributes
    ----------
    setup : Setup
        Mesh, geometry and the observed / held-out split.
    rounds : list of Round
        The baseline (round 0), every round that added an effect or a correction, and every
        backward step that took one out (:attr:`Round.removed`), in order.
    stop_reason : str
        Why the rounds ended: ``"no significant candidate"``, ``"evidence"`` or ``"cv"`` (significant
        candidates did not improve the criterion), ``"max_rounds"``, ``"given"`` (effects named by
        the user) or ``"none"``.
    ranking : list of dict
        Score test of every candidate on the baseline innovations, best first.
    last_attempt : dict
        The round that added nothing: its ``ranking``, ``threshold`` and ``tried`` (empty when the
        rounds ended otherwise).
    measured : dict
        What the data say about the wall (:func:`sfem_filters.cardiac.measured.measured_wall_kinematics`).
    reference : dict
        The thin-plate spline's held-out errors (:func:`sfem_filters.cardiac.reference.spline_reference`),
        and, when the observed points can be split into folds, its ``cross_validation`` on the
        rounds' folds, whose point indices are ``cv_folds``.
    config : dict
        The settings of the workflow.
    """

    setup: Setup
    rounds: list
    stop_reason: str
    ranking: list
    last_attempt: dict
    measured: dict
    reference: dict
    config: dict

    @property
    def baseline(self) -> Run:
        return self.rounds[0].run

    @property
    def extended(self) -> Run:
        """The final model's run (the baseline's when no effect was added)."""
        return self.rounds[-1].run

    @property
    def effects(self) -> list:
        return list(self.rounds[-1].effects)


    def as_json(self) -> dict:
        """The report as plain JSON-able values (the ``--json`` file of ``sfem-filters dense``)."""
        setup = self.setup
        ref = {k: v for k, v in self.reference.items() if k != "U"}
        return {
            "length_unit": setup.seq.units,           # unit of every *_px length: "px", or "m" for units="m"
            "noise_floor_px": setup.noise_px,
            "measured": self.measured,
            "nominal": {k: NOMINAL[k] for k in setup.nominal},
            "config": dict(self.config),
            "observed_points": setup.observed.tolist(),
            "heldout_points": setup.heldout.tolist(),
            "spline_reference": ref,
            "baseline": self.baseline.metrics,
            "extended": {"effects": self.effects, **self.extended.metrics},
            "ranking": _ranking_json(self.ranking),
            "rounds": [r.as_json() for r in self.rounds],
            "stop_reason": self.stop_reason,
            "last_attempt": {"threshold": self.last_attempt.get("threshold"), "tried": self.last_attempt.get("tried", []),
                             "ranking": _ranking_json(self.last_attempt.get("ranking", []))},
        }


def time_courses(r: Run):
    """The current effects' amplitudes over the frames, each scaled to a peak of 1, with a constant
    first: the shapes in time of the tied score test (:func:`sfem_filters.filtering.diagnostics.effect_score`).

    A regional or directional refinement of an effect in the model (one segment that does not
    contract, a fibre direction that turns) moves with that effect's time course, so its test
    needs a few coefficients per amplitude, not one per frame. ``None`` when the model has no
    effect (the baseline is tested with free amplitudes only). Shape (n_frames, 1 + effect states
    that move); frames the run did not visit are zero.
    """
    model = r.model
    if not getattr(model, "dim_eta", 0):
        return None
    h = r.result.history
    rows = h.loop_rows()
    eta = np.array([np.asarray(model.eta_of(h.x[i]), float) for i in rows])
    peak = np.max(np.abs(eta), axis=0)
    eta = eta[:, peak > 0] / peak[peak > 0]
    out = np.zeros((int(np.max(np.asarray(h.frame)[rows])) + 1, 1 + eta.shape[1]))
    out[np.asarray(h.frame)[rows]] = np.column_stack([np.ones(len(rows)), eta])
    return out


def log_evidence(r: Run) -> float:
    """``log p(y)`` of a run's model (nats), the criterion of the rounds.

    For the iterated smoother, the log-likelihood of its final pass: the model linearised at the
    mode, parameters integrated over their Gaussian prior, kinematics and effect states over
    theirs (prediction-error decomposition), i.e. the Laplace approximation of the marginal
    likelihood. For the cyclic EKF it is formed from the exact ``log p(y | theta)`` at its
    estimate and the one-cycle covariance ``Sigma``: ``log p(y | theta) + log p(theta) +
    log det(2 pi Sigma) / 2`` (:func:`sfem_filters.cardiac.measured.evaluate` computes both).
    """
    return float(r.metrics["log_evidence"])


def round_cross_validation(setup: Setup, variant: Variant, r: Run, folds: int = DEFAULT_FOLDS) -> dict:
    """Cross-validation over the observed points of a round's model (:func:`sfem_filters.cardiac.crossval.cross_validate`)
    with its material at the run's estimate; plain values (no predictions), data units, and the
    same for the model plus the spline of its residual (``residual_spline``)."""
    mat = r.model.material_of_theta(r.result.theta) if r.model.estimates_material else r.model.material
    cv = cross_validate(setup, mat, variant.effects, variant.drive, folds, drive_trend=variant.drive_trend,
                        effect_rates=variant.effect_rates, process_scale=variant.process_scale,
                        spring_scale=variant.spring_scale)
    return {**{k: cv[k] for k in ("rmse_px", "rmse_radial_px", "rmse_circumferential_px", "per_fold_px")},
            "residual_spline": cv["residual_spline"]}


def _fit(setup, variant: Variant, opts) -> Run:
    """One fit of ``variant``; ``opts["description"]`` (optional) names it on its progress bar
    (``"baseline (region map)"``, ``"round 2: + active_polar"``); the run's name is the variant's label."""
    opts = dict(opts)
    name = variant.label(variant.drive)
    description = opts.pop("description", None) or name
    if variant.material is not None:
        opts = {**opts, "parameterisation": variant.material}
    # one BLAS thread per fit, whether the fits run one after the other or side by side: the
    # threads' order of summation is then the same, and so is every figure (measured: a second
    # BLAS thread does not make a fit of the shipped slice faster, benchmarks/blas_threads.py)
    with blas_threads(1):
        out = run(setup, variant.effects, variant.drive, name=description,
                  effect_rates=variant.effect_rates, drive_trend=variant.drive_trend,
                  process_scale=variant.process_scale, spring_scale=variant.spring_scale, **opts)
    return replace(out, name=name) if isinstance(out, Run) else out


def progress_line(text: str, enabled: bool = True) -> None:
    """Write one line of progress on stderr, above any progress bar (``tqdm.write``), if ``enabled``.
    Every progress message of the rounds goes through here (``progress=False``, the command
    line's ``--quiet`` or ``--no-progress``: none)."""
    if enabled:
        tqdm.write(text, file=sys.stderr)


def _duration(seconds: float) -> str:
    """``seconds`` as ``"42 s"``, ``"3 min 05 s"`` or ``"1 h 02 min"``."""
    s = int(round(max(float(seconds), 0.0)))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {(s % 3600) // 60:02d} min"


def _gain_text(entry: dict) -> str:
    """A fitted model's evidence (and with ``criterion="cv"`` its cross-validation) against the current model."""
    out = f"evidence {entry['evidence_gain']:+.1f} nats" if np.isfinite(entry["evidence_gain"]) else "evidence n/a"
    if "cv_rmse_px" in entry:
        out += f", CV {entry['cv_rmse_px']:.3f} px"
    return out


class _Progress:
    """The rounds' progress lines (:func:`progress_line`): one as the baseline and as each round
    ends, with the held-out error so far against the spline's, the elapsed time and an upper bound
    of the time left; and, for an interruption, what had finished (:meth:`finished`)."""

    def __init__(self, enabled: bool, max_rounds: int, material: str):
        self.enabled, self.max_rounds, self.material = enabled, max_rounds, material
        self.t0 = time.perf_counter()
        self.rounds_t0 = self.round_t0 = None
        self.rounds_done = 0
        self.model = None                   # (label, held-out RMSE px) of the model so far
        self.spline_px = None

    def say(self, text: str) -> None:
        progress_line(text, self.enabled)

    def elapsed(self) -> float:
        return time.perf_counter() - self.t0

    def _heldout(self, r: "Round") -> str:
        px = float(r.run.metrics["heldout_rmse_px"])
        self.model = (r.variant.label(r.variant.drive), px)
        spline = "" if self.spline_px is None else f" (spline {self.spline_px:.3f} px)"
        return f"held-out error {px:.3f} px{spline}"

    def baseline(self, r: "Round", spline_px: float) -> None:
        self.spline_px = float(spline_px)
        self.rounds_t0 = self.round_t0 = time.perf_counter()
        material = "material fixed" if self.material == "none" else f"{self.material} map"
        self.say(f"baseline ({material}): log p(y) {r.log_evidence:.1f} nats; {self._heldout(r)}; "
                 f"elapsed {_duration(self.elapsed())}")

    def round_end(self, number: int, tried: list, added: list, stop: str | None = None) -> None:
        """Round ``number`` has ended: ``tried`` its fitted candidates and corrections, ``added`` the
        rows it appended (the kept step and its backward steps), ``stop`` why the rounds end here."""
        self.rounds_done = number
        now = time.perf_counter()
        took, self.round_t0 = now - self.round_t0, now
        tried_text = ", ".join(f"{t['effect']} (" + (f"score {t['score']:.1f}, " if t.get("score") is not None else "")
                               + f"{_gain_text(t)})" for t in tried)
        parts = ["tried " + (tried_text or "nothing")]
        for r in added:
            if getattr(r, "removed", None):
                parts.append(f"backward: took out {r.removed}")
            elif r.added is not None:
                parts.append(f"kept {r.added}")
        if stop is not None:
            parts.append(f"stopped: {stop}")
        if added or self.model is None:
            parts.append(self._heldout(added[-1]) if added else "")
        else:
            spline = "" if self.spline_px is None else f" (spline {self.spline_px:.3f} px)"
            parts.append(f"held-out error {self.model[1]:.3f} px{spline}")
        parts.append(f"elapsed {_duration(self.elapsed())}")
        left = self.max_rounds - number
        if stop is None and left > 0:
            mean = (time.perf_counter() - self.rounds_t0) / number
            parts.append(f"at most about {_duration(left * mean)} left (upper bound: {left} round"
                         f"{'s' if left > 1 else ''} left x {_duration(mean)}, the mean round so far)")
        self.say(f"round {number} ({_duration(took)}): " + "; ".join(p for p in parts if p))

    def finished(self) -> str:
        """What had finished when the rounds were interrupted, and that nothing of it is kept."""
        if self.model is None:
            done = "before the baseline fit finished"
        else:
            done = (f"after the baseline" + (f" and {self.rounds_done} round{'s' if self.rounds_done > 1 else ''}"
                                            if self.rounds_done else "")
                    + f" (model so far: {self.model[0]}, held-out error {self.model[1]:.3f} px)")
        return (f"interrupted {done}, {_duration(self.elapsed())} in; nothing is kept (the rounds keep no "
                f"checkpoint): run again to redo them")


class RoundsInterrupted(KeyboardInterrupt):
    """:func:`closing_the_loop` stopped by Ctrl-C (SIGINT): its worker processes are stopped and
    ``message`` says what had finished (:meth:`_Progress.finished`)."""

    def __init__(self, message: str):
        super().__init__(message)
        self.message = message


def _fit_job(setup, variant: Variant, opts, cv_folds) -> tuple:
    """One fit of the rounds and, when the criterion is cross-validation, its cross-validation:
    ``(run, cv or None)``. Module level, so that a worker process can run it."""
    trial = _fit(setup, variant, opts)
    return trial, (round_cross_validation(setup, variant, trial, cv_folds) if cv_folds else None)


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

    def __init__(self, setup, opts, workers: int, cv_folds, progress: bool, warm_start: bool = False):
        if opts.get("estimator") == "smoother":
            # most fits are tried and let go: the variances of their kinematics and strains are
            # made only for those kept (kept(), measured.with_covariance: the same figures)
            opts = {**opts, "covariance": False}
        self.setup, self.opts, self.workers, self.cv_folds = setup, opts, workers, cv_folds
        self.progress, self.warm_start = progress, bool(warm_start) and opts.get("estimator") == "smoother"
        self.quiet = {**opts, "progress": False}            # one bar for a batch of fits, not one per worker
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
        extra = {"warm_start": warm.result.theta} if self.warm_start and warm is not None else {}
        if iterations is not None:
            extra["max_iterations"] = min(int(iterations), int(self.opts.get("max_iterations") or iterations))
        names = [v.label(v.drive) if isinstance(v, Variant) else str(v) for v in variants] if names is None \
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
                    futures = [self.pool.submit(_fit_job, self.setup, v, {**self.quiet, **extra}, self.cv_folds)
                               for v in variants]
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
            yield _fit_job(self.setup, v, {**self.opts, **extra, "description": f"{label}: {name}"}, self.cv_folds)

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


#: Corrections of the drive the rounds may make: from the drive in use to the one tried instead.
DRIVE_CORRECTIONS = {"penalty": "contour"}

#: Corrections of the material's prior the rounds may make: from the map in use to a smoother one
#: (independent regions or elements to the smooth basis of a few modes, which ties neighbours).
MATERIAL_CORRECTIONS = {"region": "basis", "element": "basis"}

#: The corrections' factors: springs made this much stiffer (``springs:x10``), process noise this
#: much larger (``noise:x2``); a backward step (:func:`removals`) divides by the same factor.
SPRING_FACTOR, NOISE_FACTOR = 10.0, 2.0

#: |z| of the innovations' checks (NIS, lag-1 whiteness; each ~N(0, 1) for a consistent model)
#: beyond which the residual points to a correction of the model's noise or dynamics.
CHECK_Z = 3.0


def _corrections(cur: Round, material: str | None = None) -> list:
    """(name, Variant) of the corrections the current round's residual points to.

    ``drive:<new>``: the drive's correction (:data:`DRIVE_CORRECTIONS`), always a candidate.
    When the innovations are correlated in time (whiteness z above :data:`CHECK_Z`), the model
    is a frame behind the motion: ``drive:trend``, spring targets extrapolated from the two
    previous frames instead of held at the last one (also with the drive's correction,
    ``drive:<new>+trend``: the drive is one factor, its alternatives are tried side by side);
    ``effects:trend``, effect amplitudes that
    follow a trend (integrated random walks) instead of holding their last value.
    ``springs:x10``: for spring drives, the springs ten times stiffer (soft springs let the tissue
    lag its border and leave the interior to the elastic response of a few updates; on isolated
    landmarks stiff springs pull tents, which the evidence need not reject: docs, the measured slice, "A second
    split", +82 nats while the held-out error nearly doubled). Always a candidate.
    ``noise:x2``: when the innovations are too large for their covariance (NIS z above +3) and no
    effect explains them, every process noise (kinematics, drive, effects) doubled. Not the other
    way: a NIS below 1 in the smoother's final pass comes from the parameters' prior as well as
    from the process noise (a model that is right everywhere gives NIS/dof 0.5-0.8 on the
    synthetic checks), so it is no evidence that the noise is too large.
    ``material:<map>``: the material's prior made smoother (:data:`MATERIAL_CORRECTIONS`, from the
    map in use, ``material`` unless the rounds changed it), always a candidate: independent
    regions or elements let the stiffness absorb a misfit of the border that a smooth field
    cannot.
    """
    v, m = cur.variant, cur.run.metrics
    out = []
    lagged = m["lag1_z"] > CHECK_Z
    alt = DRIVE_CORRECTIONS.get(v.drive)
    if alt is not None:
        out.append((f"drive:{alt}", v.with_(drive=alt)))
    if lagged and v.drive in ("penalty", "contour") and not v.drive_trend:
        out.append(("drive:trend", v.with_(drive_trend=True)))
        if alt is not None:             # the drive's two corrections together: one alternative drive
            out.append((f"drive:{alt}+trend", v.with_(drive=alt, drive_trend=True)))
    if lagged and v.effects and not v.effect_rates:
        out.append(("effects:trend", v.with_(effect_rates=True)))
    if v.drive in ("penalty", "contour"):
        out.append(("springs:x10", v.with_(spring_scale=v.spring_scale * SPRING_FACTOR)))
    if m["nis_z"] > CHECK_Z:
        out.append(("noise:x2", v.with_(process_scale=v.process_scale * NOISE_FACTOR)))
    smoother = MATERIAL_CORRECTIONS.get(v.material if v.material is not None else material)
    if smoother is not None:
        out.append((f"material:{smoother}", v.with_(material=smoother)))
    return out


def _key(variant: Variant) -> Variant:
    """A model's identity for the rounds: its variant with the effects in a fixed order."""
    return variant.with_(effects=tuple(sorted(variant.effects)))


def removals(variant: Variant, start: Variant, loads: dict) -> list:
    """(name, Variant) of the backward steps from ``variant``: every term it holds beyond ``start``,
    taken out one at a time.

    An effect is removed (``name``: the effect; the last one out takes ``effects:trend`` with it),
    or replaced by a catalogue effect strictly nested in it (``<effect>-><nested>``: its loads span
    the nested effect's and not the other way, as six segments contain the uniform
    ``active_polar``), unless the other effects' loads already span the nested one (that would be
    a second copy of one cause). A correction is undone by one step (``drive:<drive>``: back to
    ``start``'s drive; ``drive:trend``, ``effects:trend``: off; ``springs:x10``, ``noise:x2``: the
    scale divided by that factor; ``material:<map>``: back to ``start``'s material map); ``drive:contour+trend``, one forward step, is undone in two. A
    greedy forward search can let a term enter that a later one makes unnecessary (stiffer springs
    standing in for a missing effect); these steps let the rounds take it out again (stepwise
    selection in both directions, Efroymson 1960).

    Parameters
    ----------
    variant : Variant
        The current model.
    start : Variant
        The rounds' starting model (its drive and scales are not terms).
    loads : dict
        Catalogue effect name -> load matrix (``candidate_loads``: (n_dofs, k) nodal loads per
        unit amplitude; only their column spans are used): the effects a nested replacement may
        use. Effects of ``variant`` missing from it get no nested replacement.

    Returns
    -------
    list of (str, Variant)
        Each backward step's name and the model it leads to, effects first (in ``variant``'s
        order), then the corrections.
    """
    out = []
    for e in variant.effects:
        rest = tuple(x for x in variant.effects if x != e)
        out.append((e, variant.with_(effects=rest, effect_rates=variant.effect_rates and bool(rest))))
        if e not in loads:
            continue
        others = [loads[x] for x in rest if x in loads]
        G_rest = np.column_stack(others) if others else np.zeros((loads[e].shape[0], 0))
        for c, G in loads.items():
            if (c not in variant.effects and spans(loads[e], G) and not spans(G, loads[e])
                    and not spans(G_rest, G)):
                out.append((f"{e}->{c}", variant.with_(effects=tuple(c if x == e else x for x in variant.effects))))
    if variant.drive != start.drive:
        out.append((f"drive:{variant.drive}", variant.with_(drive=start.drive)))
    if variant.drive_trend and not start.drive_trend:
        out.append(("drive:trend", variant.with_(drive_trend=False)))
    if variant.effect_rates and not start.effect_rates:
        out.append(("effects:trend", variant.with_(effect_rates=False)))
    if variant.spring_scale > start.spring_scale:
        out.append(("springs:x10", variant.with_(spring_scale=variant.spring_scale / SPRING_FACTOR)))
    if variant.process_scale > start.process_scale:
        out.append(("noise:x2", variant.with_(process_scale=variant.process_scale / NOISE_FACTOR)))
    if variant.material != start.material:
        out.append((f"material:{variant.material}", variant.with_(material=start.material)))
    return out


def closing_the_loop(seq: Sequence, effects="auto", drive: str = "penalty", landmarks: int = 8,
                     observe: str = "boundary", holdout_seed: int = 0, parameterisation: str = "region",
                     max_loops: int = 5, progress: bool = False, estimator: str = "smoother",
                     max_iterations: int | None = None, max_rounds: int = 5, alpha: float = 0.01,
                     min_evidence: float = 0.0, max_tries: int = 3, candidates=None,
                     corrections: bool = True, criterion: str = "evidence", folds: int = DEFAULT_FOLDS,
                     min_cv_gain: float = 0.01, selection: str = "best", prune: bool = True,
                     laplace: str = "gauss-newton", measurement_noise: str = "fixed",
                     mesh: str = "delaunay", angle_origin_deg: float = 0.0, workers: int | None = 1,
                     element_px: float = ELEMENT_PX, warm_start: bool = False,
                     screen_iterations: int | None = None) -> LoopResult:
    """Baseline run, then rounds of ranking and adding effects (module docstring), with the spline
    reference.

    Parameters
    ----------
    effects : "auto", "none" or a sequence (or comma-separated string) of effect names
        ``auto`` runs the rounds; ``none`` only the baseline; names: the baseline and one run with
        exactly those effects (no test); an empty sequence is ``none``. Unknown names are an error
        before any fit.
    drive, parameterisation : str
        See :func:`sfem_filters.cardiac.measured.build_model`.
    landmarks, observe, holdout_seed, mesh, element_px, angle_origin_deg :
        See :func:`sfem_filters.cardiac.measured.prepare` (``mesh="radial"``: every diagonal of the
        pixel lattice towards the cavity centre, so that the heart's position and orientation in
        the image do not change the mesh; ``mesh="polar"``: a mesh of the wall apart from the
        points, edges of about ``element_px`` point spacings, the points observed through its shape
        functions, at a cost set by the element size; ``angle_origin_deg``: where landmark 0,
        sector 0 and segment 0 start, degrees from the image's +x axis towards +y).
    warm_start : bool
        Start each fit of a round (candidates, corrections, backward steps) from the material mode
        of the model it extends or prunes instead of the prior mean (smoother only; a fit of
        another parameterisation starts from the prior). The MAP cost is the same; fewer
        Gauss-Newton iterations reach its stop rule (measured in the docs' how-to on run time).
    screen_iterations : int, optional
        Screening (smoother only): every fit of a round (candidates, corrections, backward steps)
        is first made with at most this many Gauss-Newton iterations and judged by the criterion
        there; only the one that would be kept is then fitted to the full limit (from the
        screening fit's material with ``warm_start``) and kept if it still improves the criterion.
        Warm-started from the current model's mode, where the smoother has already re-estimated
        every trajectory and effect amplitude (they are linear in the data given the material), a
        few iterations move the evidence most of its way. ``None`` (default): every fit to the
        full limit.
    estimator : {"smoother", "cyclic", "roukf"}
        The iterated smoother (at most ``max_iterations`` Gauss-Newton steps; default
        :func:`~sfem_filters.cardiac.measured.default_max_iterations` of the drive: 20, 80 under a measured pressure) or the
        paper's cyclic joint EKF (at most ``max_loops`` loops); see
        :func:`sfem_filters.cardiac.measured.run`. A fit stopped by its limit is marked not
        converged in the report: its material is where it stopped, not the posterior's mode.
    max_rounds : int
        Most forward rounds, each adding an effect or a correction (>= 1); backward steps are not
        counted.
    alpha : float
        Family-wise level of the score tests, in (0, 1).
    min_evidence : float
        Least rise of ``log p(y)`` (nats, >= 0) for an effect to be kept (``criterion="evidence"``).
    max_tries : int
        Most significant candidates fitted per round (>= 1).
    selection : {"best", "first"}
        :data:`SELECTIONS`: fit the significant candidates (at most ``max_tries``) and keep the one
        that improves the criterion most (the default), or keep the first significant candidate
        (by score) that improves it (module docstring).
    candidates : sequence of str, optional
        The catalogue names to consider (default: :data:`DEFAULT_CANDIDATES`, the catalogue
        without :data:`~sfem_filters.cardiac.effects.EXPLICIT_ONLY`).
    corrections : bool
        Also try corrections of the drive and of the effects' dynamics (:func:`_corrections`)
        when no effect passes a round.
    criterion : {"evidence", "cv"}
        What a candidate must improve to be kept (:data:`CRITERIA`): ``log p(y)`` by more than
        ``min_evidence`` nats, or the ``folds``-fold cross-validation RMSE over the observed
        points by more than the fraction ``min_cv_gain`` of its current value. Either way every
        round's model is also cross-validated, and the report gives both (with the evidence,
        only when the landmarks can be split into ``folds`` folds: at most the landmarks per
        contour, leaving at least 3 per contour outside each).
    folds : int
        Folds of the cross-validation (>= 2, :func:`sfem_filters.cardiac.crossval.observation_folds`).
    min_cv_gain : float
        Least relative fall of the cross-validation RMSE (>= 0) with ``criterion="cv"``.
    prune : bool
        After every round that adds a term, try taking out each earlier term (:func:`removals`)
        and take out the one that improves the criterion most, as long as one does (each such
        backward step is a row of the rounds, numbered with the round it followed). The
        criterion rises strictly at every step, forward or backward, so the search cannot cycle.
    laplace : {"gauss-newton", "exact"}
        The final model's material covariance: the smoother's inverse Gauss-Newton Hessian (free),
        or the exact Laplace, the inverse exact Hessian of the MAP cost at the final mode
        (:func:`sfem_filters.cardiac.measured.exact_posterior`, 2 p + 1 more gradient passes; the
        rounds' fits keep Gauss-Newton). Needs ``estimator="smoother"`` and a material map.
    measurement_noise : {"fixed", "estimate"}
        ``"estimate"``: every fit chooses the level of its measurement noise by type-II maximum
        likelihood (:func:`sfem_filters.cardiac.measured.run`) instead of taking the noise floor,
        so that the evidence compares each model at its own best level. Needs
        ``estimator="smoother"`` and ``criterion="evidence"`` (the cross-validation's folds would
        use the floor).
    workers : int or None
        How many fits of a round (its candidates, corrections, backward steps) run side by side, each
        in its own process on one BLAS thread (:func:`fit_workers`; ``None``: one per core, as far as
        the memory holds them). The rounds take the same path and give the same figures whatever the
        number: the fits are the same and are judged in the same order. The baseline is one fit.
        Default 1 (this process only, as inside a batch job whose workers are already busy).
    progress : bool
        Progress on stderr (:func:`progress_line`): a line as the baseline and each round end (what
        was tried, with its score and evidence; what was kept, or ``stopped: <reason>``; the held-out
        error so far against the spline's; the elapsed time; and an upper bound of the time left,
        the rounds left at most times the mean round so far), each fit's bar named after what it
        fits (``baseline (region map)``, ``round 2: + active_polar``), and one bar per batch of fits
        made side by side. Only stderr: the result is the same either way.

    Raises
    ------
    RoundsInterrupted
        On Ctrl-C (KeyboardInterrupt, of which it is a kind): the fits not started are cancelled,
        the worker processes terminated and the pool shut down, and ``message`` says what had
        finished (the rounds keep no checkpoint: nothing of them is kept).
    """
    if workers is not None:
        workers = integer("workers", workers, 1)
    max_iterations = default_max_iterations(drive) if max_iterations is None else integer("max_iterations",
                                                                                          max_iterations, 1)
    if measurement_noise not in NOISE_LEVELS:
        raise ValueError(f"measurement_noise: expected one of {NOISE_LEVELS}, got {measurement_noise!r}")
    if measurement_noise == "estimate" and (estimator != "smoother" or criterion != "evidence"):
        raise ValueError("measurement_noise: 'estimate' needs estimator='smoother' and criterion='evidence', got "
                         f"estimator={estimator!r}, criterion={criterion!r}")
    if criterion not in CRITERIA:
        raise ValueError(f"criterion: expected one of {CRITERIA}, got {criterion!r}")
    if laplace not in LAPLACE:
        raise ValueError(f"laplace: expected one of {LAPLACE}, got {laplace!r}")
    if laplace == "exact" and estimator != "smoother":
        raise ValueError(f"laplace: 'exact' refines the iterated smoother's posterior; expected estimator='smoother', "
                         f"got estimator={estimator!r}")
    if laplace == "exact" and parameterisation == "none":
        raise ValueError("laplace: 'exact' needs a material map; the parameterisation is 'none' (material fixed)")
    if selection not in SELECTIONS:
        raise ValueError(f"selection: expected one of {SELECTIONS}, got {selection!r}")
    min_cv_gain = non_negative("min_cv_gain", min_cv_gain)
    folds = integer("folds", folds, 2)
    max_rounds = integer("max_rounds", max_rounds, 1)
    max_tries = integer("max_tries", max_tries, 1)
    if not isinstance(prune, (bool, np.bool_)):
        raise ValueError(f"prune: expected True or False, got {prune!r}")
    min_evidence = non_negative("min_evidence", min_evidence)
    alpha = probability("alpha", alpha)
    names = list(DEFAULT_CANDIDATES) if candidates is None else list(candidates)
    unknown = [n for n in names if n not in CATALOGUE]
    if unknown:
        raise ValueError(f"candidates: unknown effects {unknown}; expected names from {sorted(CATALOGUE)}")
    if isinstance(effects, str) and effects not in ("auto", "none"):
        effects = [e.strip() for e in effects.split(",") if e.strip()]
    if not isinstance(effects, str):    # checked before any fit, not after the baseline's
        effects = list(effects)
        unknown = [e for e in effects if e not in CATALOGUE]
        if unknown:
            raise ValueError(f"effects: expected 'auto', 'none' or names from {sorted(CATALOGUE)}, got {unknown}")
        effects = effects or "none"     # an empty sequence: no effect, as "none"
    tracker = _Progress(bool(progress), max_rounds if effects == "auto" else 1, parameterisation)
    tracker.say(f"closing the loop on {seq.n_points} points x {seq.n_frames} frames: mesh and baseline fit, then "
                + ("at most {max_rounds} rounds" if effects == "auto" else "no rounds" if effects == "none"
                   else "one fit with the given effects").format(max_rounds=max_rounds))
    if not isinstance(warm_start, (bool, np.bool_)):
        raise ValueError(f"warm_start: expected True or False, got {warm_start!r}")
    if screen_iterations is not None:
        screen_iterations = integer("screen_iterations", screen_iterations, 1)
        if estimator != "smoother":
            raise ValueError(f"screen_iterations: screening stops the iterated smoother early; expected "
                             f"estimator='smoother', got {estimator!r}")
    setup = prepare(seq, landmarks, observe, holdout_seed, mesh=mesh, angle_origin_deg=angle_origin_deg,
                    element_px=element_px)
    try:                                # before any fit: can the observed points be cross-validated?
        observation_folds(setup, folds)
        cv_possible = True
    except ValueError:
        if criterion == "cv":
            raise
        cv_possible = False             # the evidence decides; rounds then report no CV
    opts = {"parameterisation": parameterisation, "max_loops": max_loops, "progress": progress,
            "estimator": estimator, "max_iterations": max_iterations, "measurement_noise": measurement_noise}
    start = Variant(drive=drive)
    fits = None
    try:
        base = _fit(setup, start, {**opts, "description": "baseline (" + ("material fixed" if parameterisation == "none"
                                                                           else f"{parameterisation} map") + ")"})
        fits = _Fits(setup, opts, 1 if effects != "auto" or workers == 1
                     else fit_workers(workers, base.model.dim_state, seq.n_frames),
                     folds if criterion == "cv" else None, progress, warm_start=warm_start)
        return _rounds(seq, setup, start, base, fits, opts, effects=effects, drive=drive, landmarks=landmarks,
                       observe=observe, holdout_seed=holdout_seed, parameterisation=parameterisation,
                       max_loops=max_loops, progress=progress, estimator=estimator, max_iterations=max_iterations,
                       max_rounds=max_rounds, alpha=alpha, min_evidence=min_evidence, max_tries=max_tries,
                       names=names, corrections=corrections, criterion=criterion, folds=folds,
                       min_cv_gain=min_cv_gain, selection=selection, prune=prune, laplace=laplace,
                       measurement_noise=measurement_noise, mesh=mesh, cv_possible=cv_possible, tracker=tracker,
                       warm_start=warm_start, screen_iterations=screen_iterations)
    except KeyboardInterrupt:
        if fits is not None:
            fits.abort()
        raise RoundsInterrupted(tracker.finished()) from None
    finally:
        if fits is not None:
            fits.close()


def _rounds(seq, setup, start, base, fits, opts, *, effects, drive, landmarks, observe, holdout_seed,
            parameterisation, max_loops, progress, estimator, max_iterations, max_rounds, alpha, min_evidence,
            max_tries, names, corrections, criterion, folds, min_cv_gain, selection, prune, laplace,
            measurement_noise, mesh, cv_possible, tracker, warm_start=False, screen_iterations=None) -> LoopResult:
    """The rounds of :func:`closing_the_loop` after its baseline fit (``fits`` makes the others;
    ``tracker``, a :class:`_Progress`, writes a line as the baseline and each round end)."""
    last = {}
    rounds = [Round(0, start, None, (), base, log_evidence=log_evidence(base),
                    cv=round_cross_validation(setup, start, base, folds) if cv_possible else None)]
    g = setup.point_geometry
    held = setup.heldout
    # the spline's held-out error, the yardstick of every round's line (the same reference as the report's)
    reference = spline_reference(seq.points, seq.displacement, setup.observed, setup.heldout,
                                 g.radial[held], g.circumferential[held])
    tracker.baseline(rounds[0], reference["heldout_rmse_px"])

    def judged(cur: Round, trial: Run, cv) -> tuple:
        """(gain, kept?, entry) of a fitted candidate under the criterion (``cv``: its
        cross-validation, made with the fit when the criterion is ``"cv"``)."""
        gain = log_evidence(trial) - cur.log_evidence
        entry = {"evidence_gain": float(gain)}
        if criterion == "cv":
            cv_gain = cur.cv["rmse_px"] - cv["rmse_px"]
            entry.update({"cv_rmse_px": cv["rmse_px"], "cv_gain_px": float(cv_gain)})
            gain, ok = cv_gain, bool(np.isfinite(cv_gain) and cv_gain > min_cv_gain * cur.cv["rmse_px"])
        else:
            ok = bool(np.isfinite(gain) and gain > min_evidence)
        return float(gain), ok, entry

    def confirmed(cur: Round, variant, trial: Run, cv, gain: float, label: str, entry: dict) -> tuple:
        """A screened fit that would be kept, fitted to the full limit: ``(run, cv, gain, ok)``;
        ``entry`` (its row of the round) gets the full fit's figures and the screening gain beside."""
        if screen_iterations is None or trial.metrics.get("converged", True):
            return trial, cv, gain, True
        full, cv = next(fits.run([variant], label, ["confirm " + variant.label(drive)], warm=trial))
        gain, ok, new = judged(cur, full, cv)
        entry.update({"screened_" + k: v for k, v in entry.items() if k in ("evidence_gain", "cv_gain_px")})
        entry.update(new)
        return full, cv, gain, ok

    def kept(number, variant, added, replaced, trial, ranking, threshold, tried, cv) -> Round:
        if getattr(trial.result, "method", "") == "iterated_smoother":
            with blas_threads(1):                      # on one BLAS thread, as its fit (_fit)
                trial = with_covariance(setup, trial)
        return Round(number, variant, added, replaced, trial, ranking, threshold, tried, log_evidence(trial),
                     cv if cv is not None or not cv_possible else round_cross_validation(setup, variant, trial, folds))
    loads = dict(candidate_loads(setup, names))
    first = diagnostics.rank_effects(base.model, base.result.history, list(loads.items()))
    if effects == "none":
        stop = "none"
    elif effects != "auto":
        chosen = start.with_(effects=tuple(effects))
        ext, cv = next(fits.run([chosen], "given effects", ["+ " + ",".join(chosen.effects)], warm=base))
        rounds.append(kept(1, chosen, ",".join(chosen.effects), (), ext, first, np.nan,
                           [{"effect": ",".join(chosen.effects), "score": None,
                             "evidence_gain": log_evidence(ext) - rounds[0].log_evidence, "accepted": True}], cv))
        stop = "given"
        tracker.round_end(1, rounds[-1].tried, rounds[-1:], "the given effects are fitted")
    else:
        stop, tests, rejected = "max_rounds", 0, set()
        # every model fitted, by its terms (effects in any order): none is fitted twice, forward or
        # backward. Each accepted step raises the criterion strictly, so a model fitted before and
        # not kept, or kept and left since, can never pass against a later one.
        seen = {_key(start)}
        n_dofs = setup.mesh.n_dofs
        for number in range(1, max_rounds + 1):
            cur = rounds[-1]
            n_before = len(rounds)
            G_cur = np.column_stack([loads[e] for e in cur.effects]) if cur.effects else np.zeros((n_dofs, 0))
            pool = [(n, G) for n, G in loads.items()
                    if n not in cur.effects and n not in rejected and not spans(G_cur, G)]
            ranking = first if number == 1 else diagnostics.rank_effects(
                cur.run.model, cur.run.result.history, pool, time_courses=time_courses(cur.run))
            ranking = [r for r in ranking if r["effect"] in dict(pool)]
            tests += sum(r.get("n_tests", 1) for r in ranking)
            threshold = -np.log10(alpha / max(tests, 1))
            tried, accepted, best = [], None, None
            # the candidates the search fits, in its order: the significant ones not fitted before,
            # at most max_tries (with selection "first", only up to the first that is kept)
            plan, planned = [], set()
            for cand in ranking:
                if cand["score"] <= threshold or len(plan) >= max_tries:
                    break
                replaced = tuple(e for e in cur.effects if spans(loads[cand["effect"]], loads[e]))
                new = tuple(e for e in cur.effects if e not in replaced) + (cand["effect"],)
                variant = cur.variant.with_(effects=new)
                if _key(variant) in seen or _key(variant) in planned:
                    continue
                planned.add(_key(variant))
                plan.append((cand, replaced, variant))
            outcomes = fits.run([v for _, _, v in plan], f"round {number}", ["+ " + c["effect"] for c, _, _ in plan],
                                warm=cur.run, iterations=screen_iterations)
            for (cand, replaced, variant), (trial, cv) in zip(plan, outcomes):
                seen.add(_key(variant))
                gain, ok, entry = judged(cur, trial, cv)
                tried.append({"effect": cand["effect"], "score": cand["score"], "test": cand.get("test", "per frame"),
                              **entry, "accepted": False})
                if not ok:
                    rejected.add(cand["effect"])
                elif best is None or gain > best[0]:
                    best = (gain, cand["effect"], replaced, variant, trial, len(tried) - 1, cv)
                if best is not None and selection == "first":
                    outcomes.close()
                    break
            if best is not None:
                gain, name, replaced, variant, trial, k, cv = best
                trial, cv, gain, ok = confirmed(cur, variant, trial, cv, gain, f"round {number}", tried[k])
                if ok:
                    tried[k]["accepted"] = True
                    accepted = kept(number, variant, name, replaced, trial, ranking, threshold, tried, cv)
                else:
                    rejected.add(name)
            if corrections and accepted is None:
                # no effect passes: every correction of the model's own drive and priors that the
                # residual points to is fitted, and the one with the largest gain of the criterion
                # is kept if the criterion improves
                # (a correction that fails here is tried again on a later round's model)
                best = None
                plan = []
                for name, variant in _corrections(cur, parameterisation):
                    if _key(variant) in seen:
                        continue
                    seen.add(_key(variant))
                    plan.append((name, variant))
                for (name, variant), (trial, cv) in zip(plan, fits.run([v for _, v in plan],
                                                                       f"round {number}, corrections",
                                                                       [f"correction {n}" for n, _ in plan],
                                                                       warm=cur.run, iterations=screen_iterations)):
                    gain, ok, entry = judged(cur, trial, cv)
                    tried.append({"effect": name, "score": None, **entry, "accepted": False})
                    if ok and (best is None or gain > best[0]):
                        best = (gain, name, variant, trial, len(tried) - 1, cv)
                if best is not None:
                    gain, name, variant, trial, k, cv = best
                    trial, cv, gain, ok = confirmed(cur, variant, trial, cv, gain, f"round {number}, corrections",
                                                    tried[k])
                    if ok:
                        tried[k]["accepted"] = True
                        accepted = kept(number, variant, name, (), trial, ranking, threshold, tried, cv)
            if accepted is None:
                stop = (criterion if any(t["score"] is not None for t in tried)
                        else "no significant candidate")
                last = {"ranking": ranking, "threshold": float(threshold), "tried": tried}
                tracker.round_end(number, tried, [], {"evidence": "no candidate or correction raised the evidence",
                                                      "cv": "no candidate or correction lowered the CV error"}
                                  .get(stop, stop))
                break
            rounds.append(accepted)
            while prune:
                # backward steps: take out the earlier term whose removal improves the criterion most
                cur = rounds[-1]
                best = None
                plan = []
                for name, variant in removals(cur.variant, start, loads):
                    if _key(variant) in seen:
                        continue
                    seen.add(_key(variant))
                    plan.append((name, variant))
                for (name, variant), (trial, cv) in zip(plan, fits.run([v for _, v in plan],
                                                                       f"round {number}, backward",
                                                                       [f"- {n}" for n, _ in plan], warm=cur.run,
                                                                       iterations=screen_iterations)):
                    gain, ok, entry = judged(cur, trial, cv)
                    cur.backward.append({"removed": name, **entry, "accepted": False})
                    if ok and (best is None or gain > best[0]):
                        best = (gain, name, variant, trial, len(cur.backward) - 1, cv)
                if best is None:
                    break
                gain, name, variant, trial, k, cv = best
                trial, cv, gain, ok = confirmed(cur, variant, trial, cv, gain, f"round {number}, backward",
                                                cur.backward[k])
                if not ok:
                    break
                cur.backward[k]["accepted"] = True
                step = kept(number, variant, None, (), trial, [], np.nan, [], cv)
                step.removed = name
                rounds.append(step)
                rejected.clear()        # an effect rejected beside the term now gone may pass without it
            tracker.round_end(number, tried, rounds[n_before:],
                              f"max_rounds ({max_rounds}) reached" if number == max_rounds else None)
    if laplace == "exact":
        rounds[-1].run = exact_posterior(setup, rounds[-1].run, progress)
    config = {"drive": drive, "landmarks": landmarks, "observe": observe, "holdout_seed": holdout_seed,
              "parameterisation": parameterisation, "estimator": estimator,
              "max_iterations" if estimator == "smoother" else "max_loops":
                  max_iterations if estimator == "smoother" else max_loops, "n_points": int(seq.n_points),
              "n_frames": int(seq.n_frames), "n_observed": int(len(setup.observed)),
              "n_heldout": int(len(setup.heldout)), "mesh_nodes": int(setup.mesh.n_nodes),
              "mesh_elements": int(setup.mesh.n_elements), "max_rounds": max_rounds, "alpha": float(alpha),
              "min_evidence": min_evidence, "max_tries": max_tries, "candidates": names,
              "corrections": bool(corrections), "criterion": criterion, "folds": folds,
              "min_cv_gain": min_cv_gain, "selection": selection, "prune": bool(prune), "laplace": laplace,
              "measurement_noise": measurement_noise, "mesh": mesh, "angle_origin_deg": setup.angle_origin_deg,
              **({"element_px": setup.element_px} if setup.element_px is not None else {}),
              **({"warm_start": True} if warm_start else {}),
              **({"screen_iterations": screen_iterations} if screen_iterations is not None else {}),
              "innovation_whitening": diagnostics.DEFAULT_WHITENING,
              "final": rounds[-1].variant.as_json()}
    if cv_possible:
        spline_cv = spline_cross_validation(setup, folds)
        reference["cross_validation"] = {k: spline_cv[k] for k in ("rmse_px", "rmse_radial_px",
                                                                   "rmse_circumferential_px", "per_fold_px")}
        reference["cv_folds"] = spline_cv["folds"]
    for r in rounds:
        r.run.metrics["versus_spline"] = versus_spline(setup, r.run.U, reference["U"])
    return LoopResult(setup=setup, rounds=rounds, stop_reason=stop, ranking=first, last_attempt=last,
                      measured=measured_wall_kinematics(setup), reference=reference, config=config)


def versus_spline(setup: Setup, U, spline_U, level: float = 0.95) -> dict | None:
    """The held-out RMSE of a model, and of the model plus the spline of its residual, minus the
    thin-plate spline's, each with a cluster interval (:func:`sfem_filters.cardiac.reference.rmse_difference`).

    The clusters are angular sectors of the held-out points, as many as landmarks per contour,
    so that a cluster spans about one gap between landmarks, the scale over which an
    interpolant's errors are alike. ``None`` when fewer than two sectors hold held-out points.

    Parameters
    ----------
    setup : Setup
    U : (F, n_points, 2) array
        The model's prediction of every point (data units).
    spline_U : (F, H, 2) array
        The spline's prediction at the held-out points (``spline_reference(...)["U"]``).
    level : float
        Confidence level of the intervals.

    Returns
    -------
    dict or None
        ``model`` and ``model_plus_spline``: each a :func:`~sfem_filters.cardiac.reference.rmse_difference`
        (data units; negative: better than the spline); ``sectors``: the number of sectors.
    """
    h = setup.heldout
    meas = setup.seq.displacement[:, h]
    angles = angle_from_origin(setup, setup.point_mesh.nodes[h])
    n = max(int(setup.n_landmarks), 2)
    sectors = angular_sectors(angles, n)
    if len(np.unique(sectors)) < 2:
        return None
    spline_res = meas - np.asarray(spline_U, float)
    out = {"sectors": n}
    for key, pred in (("model", np.asarray(U, float)[:, h]), ("model_plus_spline", kriged_heldout(setup, U)["U"])):
        out[key] = rmse_difference(meas - pred, spline_res, sectors, level)
    return out


def _variant(js: dict) -> Variant:
    """The :class:`Variant` of a round's JSON."""
    return Variant(tuple(js["effects"]), js["drive"], js["drive_trend"], js["effect_rates"], js["process_scale"],
                   js["spring_scale"], js.get("material"))


def _round_label(r: dict) -> str:
    """A round's label in the report: its number, with ``-`` for a backward step."""
    return f"{r['round']}-" if r.get("removed") else str(r["round"])


_VERSUS_LENGTHS = ("difference", "low", "high", "se", "rmse_a", "rmse_b")


def _lengths_scaled(value, factor: float, length: bool = False, versus: bool = False):
    """The report with every length multiplied by ``factor``: the values (and lists of values)
    of keys with ``_px`` in their name, and the ``difference``, ``low`` and ``high`` of a
    ``versus_spline`` entry (``difference``, ``low``, ``high``, ``se``, ``rmse_a``, ``rmse_b``)."""
    if isinstance(value, dict):
        return {k: _lengths_scaled(v, factor, length or "_px" in k or (versus and k in _VERSUS_LENGTHS),
                                   versus or k.startswith("versus_spline"))
                for k, v in value.items()}
    if isinstance(value, list):
        return [_lengths_scaled(v, factor, length, versus) for v in value]
    if length and isinstance(value, (int, float)) and not isinstance(value, bool):
        return value * factor
    return value


def length_display(units: str) -> tuple:
    """``(label, factor)`` to show lengths of a sequence with ``units`` ("px" or "m"): pixels as
    they are, metres in millimetres (``value * factor`` in ``label``)."""
    if units not in ("px", "m"):
        raise ValueError(f"units: expected 'px' or 'm', got {units!r}")
    return ("mm", 1e3) if units == "m" else ("px", 1.0)


def _number(value, width: int) -> str:
    """A report's figure to 3 decimals, or '-' where it is undefined (None or not finite)."""
    return f"{'-':>{width}}" if value is None or not np.isfinite(value) else f"{value:>{width}.3f}"


def not_converged_note(report: dict) -> str:
    """What a report's reader must know when its baseline or final fit stopped short of the stop
    rule (empty when both converged): which, and what to rerun with. ``report``:
    :meth:`LoopResult.as_json`."""
    cfg = report["config"]
    which = [key for key in ("baseline", "extended") if not report[key]["converged"]]
    if not which:
        return ""
    smoother = cfg["estimator"] == "smoother"
    limit = cfg.get("max_iterations") if smoother else cfg.get("max_loops")
    names = " and the ".join("final model" if k == "extended" else k for k in which)
    option = "--max-iterations" if smoother else "--max-loops"
    stuck = [k for k in which if report[k].get("stop_reason") == "damping"]
    why = (f"stopped at the limit of {limit} {'iterations' if smoother else 'loops'}" if not stuck else
           "stopped where no damping of the step lowered the MAP cost" if len(stuck) == len(which) else
           "stopped at the iteration limit or where no damping lowered the MAP cost")
    return (f"the {names} {why} before the material met the stop rule: the material, its sds, intervals and prior "
            f"check are where the fit stopped, not the posterior's" + (f"; rerun with a larger {option}" if not stuck
                                                                        else ""))


def format_report(result: "LoopResult") -> str:
    """Text summary of :func:`closing_the_loop`.

    Lengths are in pixels; a sequence in metres (``units = "m"``) is reported in millimetres
    (:func:`length_display`).
    """
    report = result.as_json()
    label, factor = length_display(report["length_unit"])
    if factor != 1.0:
        report = _lengths_scaled(report, factor)
        return re.sub(r"\bpx\b", label, _format_report(report))
    return _format_report(report)


def _format_report(report: dict) -> str:
    b, e = report["baseline"], report["extended"]
    cfg = report["config"]
    lines = [f"{cfg['n_points']} points, {cfg['n_frames']} frames; mesh {cfg['mesh_nodes']} nodes, "
             f"{cfg['mesh_elements']} triangles ({cfg.get('mesh', 'delaunay')}"
             + (f", edges ~{cfg['element_px']:g} px" if cfg.get("element_px") else "")
             + f"); {cfg['n_observed']} observed, {cfg['n_heldout']} held out "
             f"({cfg['landmarks']} landmarks per contour"
             + (f" from {cfg['angle_origin_deg']:g} deg" if cfg.get("angle_origin_deg", 0.0) else "")
             + f", observe {cfg['observe']}, drive {cfg['drive']}, "
             f"material {cfg['parameterisation']}, estimator {cfg['estimator']}"
             + (", fits warm-started" if cfg.get("warm_start") else "")
             + (f", screened with {cfg['screen_iterations']} iterations" if cfg.get("screen_iterations") else "")
             + ")",
             f"noise floor {report['noise_floor_px']:.3f} px" + (
                 f"; nominal (not in the file): {report['nominal']}" if report["nominal"] else ""),
             "data: wall area x{w:.3f} and wall thickness {t0:.2f} -> {tp:.2f} px at frame {f} (peak area); mean strain "
             "there E_rr {er:+.3f}, E_cc {ec:+.3f} (w.r.t. frame 0); frame 0 displacement RMS {r0:.2f} px, last-to-first "
             "{rl:.2f} px".format(w=report["measured"]["wall_area_ratio_peak"], t0=report["measured"]["wall_thickness_px_frame0"],
                                  tp=report["measured"]["wall_thickness_px_peak"], f=report["measured"]["peak_frame"],
                                  er=report["measured"]["mean_radial_strain_peak"],
                                  ec=report["measured"]["mean_circumferential_strain_peak"],
                                  r0=report["measured"]["frame0_displacement_rms_px"],
                                  rl=report["measured"]["last_to_first_rms_px"]),
             "", "ranking of candidate effects (score test on the baseline innovations; -log10 p, higher = stronger):"]
    for r in report["ranking"]:
        lines.append(f"  {r['effect']:<24} {r['score']:9.1f}   LM = {r['lm']:9.1f} on {r['df']:3d} dof, "
                     f"explains {100 * r['explained']:5.1f}% of the NIS")
    crit = ("log p(y) rises" if cfg.get("criterion", "evidence") == "evidence"
            else f"the {cfg['folds']}-fold cross-validation error over the observed points falls")
    lines += ["", f"rounds (each adds the best significant candidate while {crit}"
              + ("; a row numbered k- is a backward step after round k, taking out the term whose removal "
                 "improves it most" if cfg.get("prune") else "") + f"; CV: {cfg.get('folds')}-fold "
              "cross-validation over the observed points, material at the fit's estimate; held-out points "
              "untouched until here):",
              f"  {'round':<6}{'model':<44}{'score':>8}{'need':>7}{'dlogp(y)':>10}{'NIS/dof':>9}{'lag-1':>7}"
              f"{'CV':>7}{'held-out':>9}{'radial':>8}{'circ.':>8}{'+spline':>9}"]
    previous = None
    for r in report["rounds"]:
        tried = {t["effect"]: t for t in r["tried"]}
        t = tried.get(r["added"], {})
        score = (f"{t['score']:.1f}" + ("t" if t.get("test") == "time courses" else "")
                 if t.get("score") is not None else "-")
        need = f"{r['threshold']:.1f}" if r["threshold"] is not None else "-"
        gain = (f"{t['evidence_gain']:+.1f}" if "evidence_gain" in t else
                f"{r['log_evidence'] - previous['log_evidence']:+.1f}" if r.get("removed") else "-")
        label = _variant(r).label(cfg["drive"])
        cv = f"{r['cross_validation']['rmse_px']:.3f}" if r.get("cross_validation") else "-"
        previous = r
        lines.append(f"  {_round_label(r):<6}{label:<44}{score:>8}{need:>7}{gain:>10}"
                     f"{r['nis_mean_over_dof']:>9.3f}{r['innovation_lag1_autocorrelation']:>7.3f}{cv:>7}"
                     f"{r['heldout_rmse_px']:>9.3f}{r['heldout_rmse_radial_px']:>8.3f}"
                     f"{r['heldout_rmse_circumferential_px']:>8.3f}{r['residual_spline']['heldout_rmse_px']:>9.3f}")
    ref = report["spline_reference"]
    cv = f"{ref['cross_validation']['rmse_px']:.3f}" if ref.get("cross_validation") else "-"
    lines.append(f"  {'-':<6}{'thin-plate spline, no physics':<44}{'':>8}{'':>7}{'':>10}{'':>9}{'':>7}{cv:>7}"
                 f"{ref['heldout_rmse_px']:>9.3f}{ref['heldout_rmse_radial_px']:>8.3f}"
                 f"{ref['heldout_rmse_circumferential_px']:>8.3f}")
    lines.append("  (+spline: held-out RMSE of the model plus a thin-plate spline of its residual at the observed "
                 "points; below the spline's only where the physics adds what interpolation misses)")
    vs = [(_round_label(r), r.get("versus_spline")) for r in report["rounds"] if r.get("versus_spline")]
    if vs:
        first = vs[0][1]
        lines.append(f"  held-out RMSE minus the spline's [px], {100 * first['model']['level']:.0f}% interval (jackknife over "
                     f"{first['sectors']} angular sectors of the held-out points; negative: better than the spline):")
        for k, v in vs:
            m, p = v["model"], v["model_plus_spline"]
            lines.append(f"    round {k}: model {m['difference']:+.3f} ({m['low']:+.3f} to {m['high']:+.3f}), "
                         f"+spline {p['difference']:+.3f} ({p['low']:+.3f} to {p['high']:+.3f})")
    if any(t.get("test") == "time courses" for r in report["rounds"] for t in r["tried"]):
        lines.append("  (t: score of the test with amplitudes tied to the current effects' time courses)")
    for r in report["rounds"]:
        if r.get("backward"):
            steps = ", ".join(f"{b['removed']} {b['evidence_gain']:+.1f}"
                              + (f" (CV {b['cv_rmse_px']:.3f})" if "cv_rmse_px" in b else "")
                              + (" (taken out)" if b["accepted"] else "") for b in r["backward"])
            lines.append(f"  backward steps from round {_round_label(r)} "
                         f"(term taken out: gain in log p(y), nats"
                         + ("; CV over the observed points, px" if any("cv_rmse_px" in b for b in r["backward"]) else "")
                         + f"): {steps}")
    att = report["last_attempt"]
    rejected = [f"{t['effect']} ({t['evidence_gain']:+.1f} nats" + (f", CV {t['cv_rmse_px']:.3f} px)" if "cv_rmse_px" in t
                                                                  else ")")
                for t in att["tried"] if not t["accepted"]]
    lines.append(f"  stopped: {report['stop_reason']}" + (
        f" (needed score > {att['threshold']:.1f}; best left "
        f"{att['ranking'][0]['effect']} {att['ranking'][0]['score']:.1f})" if att["ranking"] else "")
        + (f"; fitted and rejected: {', '.join(rejected)}" if rejected else ""))
    final = report["rounds"][-1]
    lines += ["", "final model: " + _variant(final).label(cfg["drive"]),
              f"{'':<34}{'baseline':>12}{'final':>18}"]
    for key, label in (("heldout_rmse_px", "held-out RMSE [px]"), ("heldout_rmse_radial_px", "  radial [px]"),
                       ("heldout_rmse_circumferential_px", "  circumferential [px]"),
                       ("heldout_rmse_worst_frame_px", "  worst frame [px]"),
                       ("innovation_rms_px", "innovation RMS [px]"), ("nis_mean_over_dof", "mean NIS / dof (1 = consistent)"),
                       ("nis_fraction_outside_95", "frames outside 95% NIS band"),
                       ("innovation_lag1_autocorrelation", "innovation lag-1 autocorrelation"),
                       ("nis_z", "NIS z (|z| > 3: inconsistent)"), ("lag1_z", "whiteness z (|z| > 3: correlated)"),
                       ("shear_strain_rms_peak_model", "2 E_rc at peak, RMS (model)"),
                       ("shear_strain_error_rms_peak", "  error vs measured, RMS"),
                       ("shear_strain_correlation_peak", "  correlation with measured")):
        lines.append(f"{label:<34}{_number(b[key], 12)}{_number(e[key], 18)}")
        if key == "heldout_rmse_circumferential_px":
            lines.append(f"{'  model + spline of its residual':<34}{b['residual_spline']['heldout_rmse_px']:>12.3f}"
                         f"{e['residual_spline']['heldout_rmse_px']:>18.3f}")
    lines.append(f"{'2 E_rc at peak, RMS (measured)':<34}{report['measured']['shear_strain_rms_peak']:>12.3f}")
    for key, col in (("baseline", b), ("extended", e)):
        if col.get("absolute_stiffness"):
            lo, hi = col["E_level_kPa_95"]
            lines.append(f"stiffness level ({key}): {col['E_level_kPa']:.2f} kPa (95%: {lo:.2f}-{hi:.2f} kPa), "
                         "set by the measured pressure" + ("" if col["converged"] else
                                                            "; NOT CONVERGED (*): not the posterior's interval"))
    if b.get("measurement_noise_scale") is not None and e.get("measurement_noise_scale") is not None:
        lines.append(f"{'measurement noise sd / floor (ML)':<34}{np.sqrt(b['measurement_noise_scale']):>12.3f}"
                     f"{np.sqrt(e['measurement_noise_scale']):>18.3f}")
    smoother = cfg["estimator"] == "smoother"
    label = "iterations (* not converged)" if smoother else "loops (* material not converged)"
    lines.append(f"{label:<34}"
                 + "".join(f"{str(r['loops']) + ('' if r['converged'] else '*'):>{w}}" for r, w in ((b, 12), (e, 18))))
    note = not_converged_note(report)
    if note:
        lines.append(f"  * {note}")
    if b.get("material_drift_sd") is not None and e.get("material_drift_sd") is not None:
        label = "last material step / sd" if smoother else "last loop material step / sd"
        lines.append(f"{label:<34}{b['material_drift_sd']:>12.3f}{e['material_drift_sd']:>18.3f}")
    if b.get("E_sd_log_median") is not None and e.get("E_sd_log_median") is not None:
        lines.append(f"{'posterior sd of log E (median)':<34}{b['E_sd_log_median']:>12.3f}{e['E_sd_log_median']:>18.3f}")
        lines.append(f"{'posterior sd of nu (median)':<34}{b['nu_sd_median']:>12.3f}{e['nu_sd_median']:>18.3f}")
    if cfg.get("laplace") == "exact" and e.get("material_covariance") is not None:
        x = e.get("exact_laplace") or {}
        lines.append("final material covariance: " + ("the exact Laplace (inverse exact Hessian of the MAP cost)"
                                                      if e["material_covariance"] == "exact" else
                                                      "Gauss-Newton (the exact Hessian is not positive definite)"))
        if x:
            lo, hi = x["relative_eigenvalues"]
            line = f"  exact Hessian / Gauss-Newton: eigenvalues {lo:.3f} to {hi:.3f} ({x['gradient_passes']} gradient passes)"
            if x["E_sd_log_ratio"] is not None:
                line += ("; sd exact / Gauss-Newton: log E {:.2f}-{:.2f}, nu {:.2f}-{:.2f}"
                         .format(*x["E_sd_log_ratio"], *x["nu_sd_ratio"]))
            lines.append(line)
    if b.get("prior_conflict") and e.get("prior_conflict"):
        lines.append(f"{'material vs its prior, -log10 p':<34}{max(0.0, -b['prior_conflict']['log10_p']):>12.1f}"
                     f"{max(0.0, -e['prior_conflict']['log10_p']):>18.1f}")
        for key, pc in (("baseline", b["prior_conflict"]), ("final", e["prior_conflict"])):
            if pc["flagged"]:
                items = "; ".join(f"{f['quantity']} in {f['where']} "
                                  + (f"(E x {f['estimate']:.3g}" if f["quantity"] == "log E" else f"(nu {f['estimate']:.3f}")
                                  + f", z {f['z']:+.1f})" for f in pc["flagged"][:3])
                lines.append(f"  prior-data conflict, {key} ({pc['n_flagged']} beyond |z| {pc['threshold']:.1f}): {items}")
    if b.get("strain_sd_median") is not None and e.get("strain_sd_median") is not None:
        for k, name in enumerate(("E_rr", "E_cc", "2 E_rc")):
            lines.append(f"{'strain sd ' + name + ' (median)':<34}{b['strain_sd_median'][k]:>12.4f}"
                         f"{e['strain_sd_median'][k]:>18.4f}")
    if "active_polar[0]" in e.get("effect_state_names", []):
        offset = e["effect_state_names"].index("active_polar[0]")
        st = np.array(e["effect_states"])[:, offset:offset + 2]
        peak = int(np.argmax(np.abs(st[:, 1])))
        eps = equivalent_eigenstrain(st[peak])
        lines.append(f"active_polar at frame {peak}: a_c = {st[peak, 0]:.3f}, a_r = {st[peak, 1]:.3f} (x E0), "
                     f"equivalent eigenstrain eps_cc = {eps[0]:+.3f}, eps_rr = {eps[1]:+.3f}")
    return "\n".join(lines)
