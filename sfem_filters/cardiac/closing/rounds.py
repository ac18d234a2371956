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

from ..._validate import integer
from ...filtering import diagnostics
from ...resources import blas_threads, frame_threads, usable_cores
from ..crossval import observation_folds, spline_cross_validation
from ..measured import Run, exact_posterior, measured_wall_kinematics, prepare, with_covariance
from ..reference import spline_reference
from ..sequence import Sequence
from ..specs import EstimatorSettings, LoopSettings, ModelSpec, check_specs
from .criteria import log_evidence, round_cross_validation, time_courses, versus_spline
from .moves import _corrections, _key, candidate_loads, removals, spans
from .progress import RoundsInterrupted, _Progress
from .records import LoopResult, Round
from .workers import _Fits, _fit, fit_workers

__all__ = ["closing_the_loop"]


def closing_the_loop(seq: Sequence, model: ModelSpec = ModelSpec(), estimator: EstimatorSettings = EstimatorSettings(),
                     loop: LoopSettings = LoopSettings(), *, workers: int | None = 1,
                     progress: bool = False) -> LoopResult:
    """Baseline run, then rounds of ranking and adding effects (module docstring), with the spline
    reference.

    Parameters
    ----------
    seq : Sequence
        The measured motion (:func:`~sfem_filters.cardiac.load_sequence`).
    model : ModelSpec
        What model is fitted (:class:`~sfem_filters.cardiac.specs.ModelSpec`): the set-up (mesh,
        landmarks, observed points, held-out split, angle origin; see
        :func:`sfem_filters.cardiac.measured.prepare`), the drive and the material map the rounds start
        from (:func:`sfem_filters.cardiac.measured.build_model`). The baseline is this model; it has
        no effects and no material changed by the rounds (both an error): the rounds add them.
    estimator : EstimatorSettings
        How each model is fitted (:class:`~sfem_filters.cardiac.specs.EstimatorSettings`): the
        iterated smoother or the cyclic filters, their limits, the final posterior and the
        measurement noise; see :func:`sfem_filters.cardiac.measured.run`. A fit stopped by its limit
        is marked not converged in the report: its material is where it stopped, not the posterior's
        mode.
    loop : LoopSettings
        How the rounds search (:class:`~sfem_filters.cardiac.specs.LoopSettings`): which effects
        (``"auto"``: the rounds; ``"none"``: the baseline only; names: the baseline and one fit with
        exactly those, no test), the candidates, the score tests' level, the criterion, the
        corrections, the backward steps, and the search's shortcuts (warm starts, screening).
    workers : int or None
        How many fits of a round (its candidates, corrections, backward steps) run side by side, each
        in its own process on one BLAS thread (:func:`fit_workers`; ``None``: one per core, as far as
        the memory holds them). The rounds take the same path and give the same figures whatever the
        number: the fits are the same and are judged in the same order. The baseline is one fit;
        it and the other fits made in this process (a kept fit's confirmation and covariance) take
        each linearisation's frames on as many threads as this allows, up to the usable cores
        (:class:`~sfem_filters.resources.frame_threads`, the same figures). Default 1 (this process
        only, one thread, as inside a batch job whose workers are already busy).
    progress : bool
        Progress on stderr (:func:`progress_line`): a line as the baseline and each round end (what
        was tried, with its score and evidence; what was kept, or ``stopped: <reason>``; the held-out
        error so far against the spline's; the elapsed time; and an upper bound of the time left,
        the rounds left at most times the mean round so far), each fit's bar named after what it
        fits (``baseline (region map)``, ``round 2: + active_polar``), and one bar per batch of fits
        made side by side. Only stderr: the result is the same either way.

    Raises
    ------
    TypeError
        A setting that is not a spec of its kind (``model`` not a :class:`ModelSpec`, ...).
    ValueError
        Settings that ask something of each other they cannot have
        (:func:`~sfem_filters.cardiac.specs.check_specs`), before any fit.
    RoundsInterrupted
        On Ctrl-C (KeyboardInterrupt, of which it is a kind): the fits not started are cancelled,
        the worker processes terminated and the pool shut down, and ``message`` says what had
        finished (the rounds keep no checkpoint: nothing of them is kept).

    Examples
    --------
    >>> from sfem_filters.cardiac import EstimatorSettings, LoopSettings, ModelSpec, annulus_sequence
    >>> seq = annulus_sequence(None, n_frames=4, seed=0)
    >>> out = closing_the_loop(seq, ModelSpec(landmarks=6), EstimatorSettings(max_iterations=2),
    ...                        LoopSettings(effects="none"))
    >>> [r.change for r in out.rounds], out.config["landmarks"], out.config["max_iterations"]
    (['baseline'], 6, 2)
    """
    check_specs(model, estimator, loop)
    if workers is not None:
        workers = integer("workers", workers, 1)
    estimator = estimator.with_(max_iterations=estimator.iteration_limit(model.drive))
    effects, criterion, folds = loop.effects, loop.criterion, loop.folds
    tracker = _Progress(bool(progress), loop.max_rounds if effects == "auto" else 1, model.parameterisation)
    tracker.say(f"closing the loop on {seq.n_points} points x {seq.n_frames} frames: mesh and baseline fit, then "
                + ("at most {max_rounds} rounds" if effects == "auto" else "no rounds" if effects == "none"
                   else "one fit with the given effects").format(max_rounds=loop.max_rounds))
    setup = prepare(seq, model.landmarks, model.observe, model.holdout_seed, mesh=model.mesh,
                    angle_origin_deg=model.angle_origin_deg, element_px=model.element_px)
    try:                                # before any fit: can the observed points be cross-validated?
        observation_folds(setup, folds)
        cv_possible = True
    except ValueError:
        if criterion == "cv":
            raise
        cv_possible = False             # the evidence decides; rounds then report no CV
    start = model
    parameterisation = model.parameterisation
    # the fits made in this process (the baseline, a kept fit's confirmation and covariance) come one
    # at a time while any worker waits: they take each linearisation's frames on the cores the run
    # may use (the same figures; workers=1, as in a batch job, keeps them on one)
    threads = 1 if workers == 1 else min(workers or usable_cores(), usable_cores())
    fits = None
    try:
        base = _fit(setup, start, estimator, progress=progress, threads=threads,
                    description="baseline (" + ("material fixed" if parameterisation == "none"
                                                else f"{parameterisation} map") + ")")
        fits = _Fits(setup, estimator, 1 if effects != "auto" or workers == 1
                     else fit_workers(workers, base.model.dim_state, seq.n_frames),
                     folds if criterion == "cv" else None, progress, warm_start=loop.warm_start, threads=threads)
        return _rounds(seq, setup, start, base, fits, estimator, loop, cv_possible=cv_possible, tracker=tracker,
                       progress=progress)
    except KeyboardInterrupt:
        if fits is not None:
            fits.abort()
        raise RoundsInterrupted(tracker.finished()) from None
    finally:
        if fits is not None:
            fits.close()


def _rounds(seq, setup, start: ModelSpec, base, fits, estimator: EstimatorSettings, loop: LoopSettings, *,
            cv_possible: bool, tracker, progress: bool = False) -> LoopResult:
    """The rounds of :func:`closing_the_loop` after its baseline fit (``fits`` makes the others;
    ``tracker``, a :class:`_Progress`, writes a line as the baseline and each round end; ``start``: the
    baseline's model, ``estimator`` with its iteration limit resolved)."""
    effects, drive, parameterisation, names = loop.effects, start.drive, start.parameterisation, list(loop.candidates)
    criterion, folds, screen_iterations = loop.criterion, loop.folds, loop.screen_iterations
    max_rounds = loop.max_rounds
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
            gain, ok = cv_gain, bool(np.isfinite(cv_gain) and cv_gain > loop.min_cv_gain * cur.cv["rmse_px"])
        else:
            ok = bool(np.isfinite(gain) and gain > loop.min_evidence)
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
            with blas_threads(1), frame_threads(fits.threads):     # as its fit (_fit)
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
            threshold = -np.log10(loop.alpha / max(tests, 1))
            tried, accepted, best = [], None, None
            # the candidates the search fits, in its order: the significant ones not fitted before,
            # at most max_tries (with selection "first", only up to the first that is kept)
            plan, planned = [], set()
            for cand in ranking:
                if cand["score"] <= threshold or len(plan) >= loop.max_tries:
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
                if best is not None and loop.selection == "first":
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
            if loop.corrections and accepted is None:
                # no effect passes: every correction of the model's own drive and priors that the
                # residual points to is fitted, and the one with the largest gain of the criterion
                # is kept if the criterion improves
                # (a correction that fails here is tried again on a later round's model)
                best = fitted_best(cur, _corrections(cur, loop.stiff_springs),
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
            while loop.prune:
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
    if estimator.laplace == "exact":
        rounds[-1].run = exact_posterior(setup, rounds[-1].run, progress)
    model, smoother = start, estimator.estimator == "smoother"
    config = {"drive": drive, "landmarks": model.landmarks, "observe": model.observe,
              "holdout_seed": model.holdout_seed, "parameterisation": parameterisation,
              "estimator": estimator.estimator,
              "max_iterations" if smoother else "max_loops": estimator.max_iterations if smoother
              else estimator.max_loops, "n_points": int(seq.n_points),
              "n_frames": int(seq.n_frames), "n_observed": int(len(setup.observed)),
              "n_heldout": int(len(setup.heldout)), "mesh_nodes": int(setup.mesh.n_nodes),
              "mesh_elements": int(setup.mesh.n_elements), "max_rounds": max_rounds, "alpha": float(loop.alpha),
              "min_evidence": loop.min_evidence, "max_tries": loop.max_tries, "candidates": names,
              "corrections": loop.corrections, "stiff_springs": loop.stiff_springs, "criterion": criterion,
              "folds": folds, "min_cv_gain": loop.min_cv_gain, "selection": loop.selection, "prune": loop.prune,
              "laplace": estimator.laplace, "measurement_noise": estimator.measurement_noise, "mesh": model.mesh,
              "angle_origin_deg": setup.angle_origin_deg,
              # the report's record of the run (the batch fingerprint hashes the specs whole, dense_config)
              **({"element_px": setup.element_px} if setup.element_px is not None else {}),
              **({"warm_start": True} if loop.warm_start else {}),
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
