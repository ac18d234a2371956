"""Closing the loop on measured data: residual diagnosis, missing effects added round by round.

Step 5 of the paper's section 3.2 workflow, on top of :mod:`sfem_filters.cardiac.measured`:
:func:`closing_the_loop` fits the baseline, then in rounds scores the catalogue's candidates on the
current model's innovations, fits the significant ones, keeps the one that improves the criterion
most (the evidence ``log p(y)``, or cross-validation over the observed points), tries corrections of
the model's drive and priors when no effect passes, and steps backward after every addition.
The search and its criteria are told in the module docstring of :mod:`.rounds` and in the docs'
explanation page "Closing the loop and its criteria" (``docs/explanation/closing_loop.md``).

A round's model is a :class:`~sfem_filters.cardiac.specs.ModelSpec`: the settings' model with the
effects and corrections the rounds made. The search moves between models, forward by an effect or a
correction and backward by :func:`removals`; a fit of a model is judged by :func:`log_evidence` (or
:func:`round_cross_validation`):

>>> from sfem_filters.cardiac import ModelSpec
>>> from sfem_filters.cardiac.closing import SEARCHES, removals
>>> v = ModelSpec(("active_segments",), effect_rates=True, spring_scale=10.0)   # two rounds' additions
>>> v.label("penalty")
'active_segments [effect trend] [springs x10]'
>>> [name for name, _ in removals(v, ModelSpec(), loads={})]      # the backward steps from v
['active_segments', 'effects:trend', 'springs:x10']
>>> SEARCHES["fast"].max_iterations("penalty")                  # the default search's iteration limit
40

A whole run (:func:`closing_the_loop`) is in the walk-through of :mod:`sfem_filters.cardiac`.

The package's parts, each importing only those before it:

* :mod:`.records`: the searches (:data:`SEARCHES`), a round (:class:`Round`) and the outcome
  (:class:`LoopResult`); the settings are the specs of :mod:`sfem_filters.cardiac.specs`;
* :mod:`.criteria`: :func:`log_evidence`, :func:`round_cross_validation`, :func:`time_courses`
  (the tied score test's shapes) and :func:`versus_spline`;
* :mod:`.progress`: the progress lines (:func:`progress_line`) and :class:`RoundsInterrupted`;
* :mod:`.workers`: one fit (``_fit``), and a round's fits serially or in worker processes
  (``_Fits``, :func:`fit_workers`);
* :mod:`.moves`: the candidates' loads (:func:`candidate_loads`, :func:`spans`), the corrections
  (``_corrections``) and the backward steps (:func:`removals`);
* :mod:`.rounds`: :func:`closing_the_loop` and its rounds;
* :mod:`.report`: :func:`format_report` and the report's helpers.

Every name of the parts is also a name of this package, as when it was one module (the code
looks a name up in the part that uses it: replace it there).
"""
from __future__ import annotations

# every name of the one module closing.py was, for the code and tests that use them from here
from ...filtering import diagnostics
from ...filtering.smoother import PEAK_FACTOR, WORKING
from ...resources import process_pool, usable_cores
from ..measured import run
from . import criteria, moves, progress, records, report, rounds, workers
from .criteria import log_evidence, round_cross_validation, time_courses, versus_spline
from .moves import (_SPAN_TOL, CHECK_Z, DRIVE_CORRECTIONS, MATERIAL_CORRECTIONS, NOISE_FACTOR, SPRING_FACTOR,
                    STIFF_SPRINGS, _corrections, _key, candidate_loads, removals, spans)
from .progress import RoundsInterrupted, _duration, _gain_text, _Progress, progress_line
from .records import (_ROUND_KEYS, CRITERIA, DEFAULT_CANDIDATES, LAPLACE, SEARCHES, SELECTIONS, LoopResult, Round,
                      Search, _ranking_json)
from .report import (_VERSUS_LENGTHS, _format_report, _lengths_scaled, _number, _round_label, _variant,
                     format_report, length_display, not_converged_note)
from .rounds import _rounds, closing_the_loop
from .workers import _fit, _Fits, _fit_job, fit_workers

__all__ = ["LoopResult", "Round", "closing_the_loop", "candidate_loads", "spans", "log_evidence",
           "format_report", "removals", "fit_workers", "usable_cores", "versus_spline", "SELECTIONS",
           "DRIVE_CORRECTIONS", "time_courses", "CRITERIA", "round_cross_validation", "DEFAULT_CANDIDATES", "LAPLACE",
           "length_display", "not_converged_note", "progress_line", "RoundsInterrupted", "STIFF_SPRINGS",
           "SEARCHES"]
