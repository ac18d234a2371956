"""What the rounds are made of: the searches, a round (:class:`Round`, its model a
:class:`~sfem_filters.cardiac.specs.ModelSpec`) and the outcome (:class:`LoopResult`); the settings'
choices (:data:`CRITERIA`, :data:`SELECTIONS`, ...) are those of :mod:`sfem_filters.cardiac.specs`."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..measured import ELEMENT_PX, NOMINAL, Run, Setup, default_max_iterations
from ..specs import CRITERIA, DEFAULT_CANDIDATES, LAPLACE, SELECTIONS, ModelSpec

__all__ = ["Search", "SEARCHES", "SELECTIONS", "CRITERIA", "LAPLACE", "DEFAULT_CANDIDATES", "Round", "LoopResult"]


@dataclass(frozen=True)
class Search:
    """How thoroughly the rounds search, and on what mesh (the settings of the same names of
    :class:`~sfem_filters.cardiac.specs.ModelSpec` and :class:`~sfem_filters.cardiac.specs.LoopSettings`;
    ``max_iterations`` None: :func:`~sfem_filters.cardiac.measured.default_max_iterations`
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
        """This search's settings by their specs' field names (beside ``max_iterations``; ``mesh`` and
        ``element_px`` of :class:`~sfem_filters.cardiac.specs.ModelSpec`, the others of
        :class:`~sfem_filters.cardiac.specs.LoopSettings`; :func:`~sfem_filters.cardiac.specs.specs_from`
        sorts them)."""
        return {"mesh": self.mesh, "element_px": self.element_px, "warm_start": self.warm_start,
                "screen_iterations": self.screen_iterations}


#: The searches the ``dense`` command offers (``--search``). ``coarse``, the default: a mesh of the
#: wall apart from the points (2-pixel edges), every fit of a round started from the current model's
#: mode and screened with 3 Gauss-Newton iterations, only the one kept fitted to the end, and room for
#: the baseline to converge (40 iterations). ``fast``: the same on the node-per-point mesh, a few times
#: slower; the same path, final model and held-out errors as ``full`` on the measured slice and on
#: synthetic checks drawn on that mesh. ``full``: every fit to the end from the prior on the
#: node-per-point mesh (what the command did before the searches). On synthetic checks drawn on a
#: finer mesh than any estimator's, coarse finds the true effects where fast and full add one; on
#: checks drawn on the node-per-point mesh (fast's and full's own discretisation) it finds others.
#: The docs' validation page "Closing the loop: the coarse and fast searches" measures what each finds and costs.
SEARCHES = {"fast": Search(warm_start=True, screen_iterations=3, min_iterations=40),
            "coarse": Search(mesh="polar", warm_start=True, screen_iterations=3, min_iterations=40),
            "full": Search()}


@dataclass(eq=False)
class Round:
    """One round of :func:`closing_the_loop`.

    Attributes
    ----------
    number : int
        0 for the baseline.
    variant : ModelSpec
        The round's model (:class:`~sfem_filters.cardiac.specs.ModelSpec`).
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
    variant: ModelSpec
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
        """Names of the effects of the round's model (``variant.effects``)."""
        return self.variant.effects

    @property
    def change(self) -> str:
        """What the round changed: ``+ <added>``, ``- <removed>``, or ``baseline``."""
        if self.removed is not None:
            return f"- {self.removed}"
        return "baseline" if self.added is None else f"+ {self.added}"

    def as_json(self) -> dict:
        """The round as plain JSON-able values (an entry of ``rounds`` in :meth:`LoopResult.as_json`).

        Returns
        -------
        dict
            ``round`` (its number), the model's settings (:meth:`~sfem_filters.cardiac.specs.ModelSpec.as_json`),
            ``added``, ``removed``, ``backward``, ``replaced``, ``log_evidence`` (nats), ``threshold`` (None
            when not finite), ``tried``, ``cross_validation``, ``ranking``, the run's held-out errors (px),
            innovation and shear-strain diagnostics, and ``versus_spline``.
        """
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
        The settings of the workflow, as the report records them.
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
        """The run of round 0, the baseline model."""
        return self.rounds[0].run

    @property
    def extended(self) -> Run:
        """The final model's run (the baseline's when no effect was added)."""
        return self.rounds[-1].run

    @property
    def effects(self) -> list:
        """Names of the final model's effects (those of the last round)."""
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
