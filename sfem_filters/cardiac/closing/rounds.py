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

import numpy as np

from ..._validate import integer, non_negative, probability
from ...filtering import diagnostics
from ...filtering.iterated import NOISE_LEVELS
from ...resources import blas_threads
from ..crossval import DEFAULT_FOLDS, observation_folds, spline_cross_validation
from ..effects import CATALOGUE
from ..measured import (ELEMENT_PX, Run, default_max_iterations, exact_posterior, measured_wall_kinematics,
                        prepare, with_covariance)
from ..reference import spline_reference
from ..sequence import Sequence
from .criteria import log_evidence, round_cross_validation, time_courses, versus_spline
from .moves import STIFF_SPRINGS, _corrections, _key, candidate_loads, removals, spans
from .progress import RoundsInterrupted, _Progress
from .records import CRITERIA, DEFAULT_CANDIDATES, LAPLACE, SELECTIONS, LoopResult, Round, Variant
from .workers import _Fits, _fit, fit_workers

__all__ = ["closing_the_loop"]


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
                     screen_iterations: int | None = None, stiff_springs: str = "contour") -> LoopResult:
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
    stiff_springs : {"contour", "any"}
        :data:`STIFF_SPRINGS`: which drives the correction ``springs:x10`` (springs ten times
        stiffer) is offered to. ``"contour"`` (default): only to springs spread along the whole
        contour (``drive="contour"``); on isolated landmarks stiff springs pull tents in the wall
        that the evidence can reward while the held-out error grows (the docs' validation page
        "Stiff springs only along the contours" measures both). ``"any"``: to the landmark
        springs of ``drive="penalty"`` too (what the rounds did before).
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
    if stiff_springs not in STIFF_SPRINGS:
        raise ValueError(f"stiff_springs: expected one of {STIFF_SPRINGS}, got {stiff_springs!r}")
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
                       warm_start=warm_start, screen_iterations=screen_iterations, stiff_springs=stiff_springs)
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
            measurement_noise, mesh, cv_possible, tracker, warm_start=False, screen_iterations=None,
            stiff_springs="contour") -> LoopResult:
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

    def fitted_best(cur: Round, steps, label: str, prefix: str, row, rows: list):
        """Fit the steps ``(name, variant)`` (corrections or backward steps) not fitted before, in their
        order, each judged against ``cur`` and its row (``row(name)``, then the judgement) appended to
        ``rows``: the one with the largest gain of those that improve the criterion, ``(gain, name,
        variant, run, row index, cv)``, or None. Their fits are named ``prefix + name`` after ``label``."""
        best, plan = None, []
        for name, variant in steps:
            if _key(variant) in seen:
                continue
            seen.add(_key(variant))
            plan.append((name, variant))
        for (name, variant), (trial, cv) in zip(plan, fits.run([v for _, v in plan], label,
                                                               [prefix + n for n, _ in plan], warm=cur.run,
                                                               iterations=screen_iterations)):
            gain, ok, entry = judged(cur, trial, cv)
            rows.append({**row(name), **entry, "accepted": False})
            if ok and (best is None or gain > best[0]):
                best = (gain, name, variant, trial, len(rows) - 1, cv)
        return best

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
                best = fitted_best(cur, _corrections(cur, parameterisation, stiff_springs),
                                   f"round {number}, corrections",
                                   "correction ", lambda name: {"effect": name, "score": None}, tried)
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
                best = fitted_best(cur, removals(cur.variant, start, loads), f"round {number}, backward", "- ",
                                   lambda name: {"removed": name}, cur.backward)
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
              "corrections": bool(corrections), "stiff_springs": stiff_springs, "criterion": criterion,
              "folds": folds,
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
