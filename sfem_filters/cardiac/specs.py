"""The settings of closing the loop, as three small frozen specs.

:func:`~sfem_filters.cardiac.closing_the_loop` takes a sequence and three settings, each a frozen,
validated dataclass, each setting in exactly one of them:

* :class:`ModelSpec`: what model is fitted: the set-up (mesh, observed landmarks, the held-out
  split, where angles start), the drive and its springs, the material map, the process noise and the
  effects. A round of the loop is a model too: ``spec.with_(effects=...)``; the rounds change only
  its effects, drive, trends, scales and material map (:meth:`ModelSpec.as_json`).
* :class:`EstimatorSettings`: how one model is fitted: the estimator and its limits, the final
  posterior, the measurement noise.
* :class:`LoopSettings`: how the rounds search: which effects, the score tests' level, the
  criterion, the corrections, the backward steps, and the shortcuts of the search (warm starts,
  screening).

Every spec checks its values when made (a bad value is a ``ValueError`` naming the field and what
was expected) and has a JSON round trip (``to_json`` / ``from_json``, every field, no key left out
at its default): a batch job's fingerprint hashes the three JSONs whole
(:func:`sfem_filters.batch.dense_config`). :func:`check_specs` checks what one spec asks of another.

>>> from sfem_filters.cardiac.specs import EstimatorSettings, LoopSettings, ModelSpec
>>> model = ModelSpec(drive="contour", landmarks=6)
>>> model.with_(effects=("active_polar",)).label("penalty")
'active_polar [drive contour]'
>>> ModelSpec.from_json(model.to_json()) == model
True
>>> LoopSettings(effects="active_polar, cavity_pressure").effects
('active_polar', 'cavity_pressure')
>>> EstimatorSettings().iteration_limit("pressure")       # the drive's default limit
80
>>> LoopSettings(alpha=2.0)
Traceback (most recent call last):
...
ValueError: alpha: expected a number in the open interval (0, 1), got 2.0
"""
from __future__ import annotations

from dataclasses import KW_ONLY, asdict, dataclass, fields, replace

import numpy as np

from .._validate import integer, non_negative, positive, probability
from ..filtering.iterated import NOISE_LEVELS
from .crossval import DEFAULT_FOLDS
from .effects import CATALOGUE, EXPLICIT_ONLY
from .measured import (DRIVES, ELEMENT_PX, ESTIMATORS, MESHES, OBSERVE, PARAMETERISATIONS,
                       default_max_iterations)

__all__ = ["ModelSpec", "EstimatorSettings", "LoopSettings", "check_specs", "specs_from", "SELECTIONS", "CRITERIA",
           "LAPLACE", "STIFF_SPRINGS", "DEFAULT_CANDIDATES"]

#: How a round picks among significant candidates (``LoopSettings.selection``, ``--selection``): the
#: first by score that improves the criterion, or the best of those fitted.
SELECTIONS = ("first", "best")

#: What decides whether a candidate is kept (``LoopSettings.criterion``, ``--criterion``): the evidence
#: ``log p(y)`` of the observed points, or K-fold cross-validation over them
#: (:mod:`sfem_filters.cardiac.crossval`).
CRITERIA = ("evidence", "cv")

#: The final model's material covariance (``EstimatorSettings.laplace``, ``--laplace``): the smoother's
#: inverse Gauss-Newton Hessian, or the inverse exact Hessian of the MAP cost at the mode.
LAPLACE = ("gauss-newton", "exact")

#: Which drives the correction ``springs:x10`` is offered to (``LoopSettings.stiff_springs``,
#: ``--stiff-springs``): ``"contour"``, springs spread along the whole contour only (the default);
#: ``"any"``, the isolated landmarks' springs (``drive="penalty"``) too.
STIFF_SPRINGS = ("contour", "any")

#: The candidates of the rounds when none are given: the catalogue without the effects that are
#: tried only by name (:data:`~sfem_filters.cardiac.effects.EXPLICIT_ONLY`).
DEFAULT_CANDIDATES = tuple(sorted(n for n in CATALOGUE if n not in EXPLICIT_ONLY))


def _choice(name: str, value, choices) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name}: expected one of {tuple(choices)}, got {value!r}")
    return value


def _flag(name: str, value) -> bool:
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: expected True or False, got {value!r}")
    return bool(value)


def _number(name: str, value, check, *args) -> float:
    """``check(name, value, *args)`` of :mod:`sfem_filters._validate`, a ``ValueError`` for a value
    that is no number at all (a spec's every bad value is a ``ValueError``)."""
    try:
        return check(name, value, *args)
    except TypeError as exc:
        raise ValueError(str(exc)) from None


def _finite(name: str, value, unit: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = np.nan
    if isinstance(value, (bool, np.bool_)) or not np.isfinite(v):
        raise ValueError(f"{name}: expected a finite number in {unit}, got {value!r}")
    return v


def _names(name: str, value, what: str) -> tuple:
    """Catalogue effect names from a sequence or a comma-separated string, as a tuple."""
    if isinstance(value, str):
        value = [e.strip() for e in value.split(",") if e.strip()]
    try:
        value = tuple(value)
    except TypeError:
        raise ValueError(f"{name}: expected {what}, got {value!r}") from None
    unknown = [e for e in value if not isinstance(e, str) or e not in CATALOGUE]
    if unknown:
        raise ValueError(f"{name}: expected {what}, got {unknown}")
    return value


class _Spec:
    """The JSON round trip and ``with_`` shared by the specs (each a frozen dataclass)."""

    def with_(self, **change):
        """A copy with the given fields changed (checked as a new spec)."""
        return replace(self, **change)

    def to_json(self) -> dict:
        """Every field as a JSON value (tuples as lists), defaults included."""
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_json(cls, js: dict):
        """The spec of :meth:`to_json`'s dict; a field missing takes its default, an unknown key is an error."""
        if not isinstance(js, dict):
            raise ValueError(f"{cls.__name__}: expected a dict of fields, got {type(js).__name__}")
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(js) - set(names))
        if unknown:
            raise ValueError(f"{cls.__name__}: unknown fields {unknown}; expected fields among {names}")
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in js.items()})

    def _set(self, name: str, value) -> None:
        object.__setattr__(self, name, value)


@dataclass(frozen=True)
class ModelSpec(_Spec):
    """What model is fitted: its effects, drive, noise and material, and the set-up it is fitted on.

    The first seven fields are what the rounds of :func:`~sfem_filters.cardiac.closing_the_loop`
    change (a round's model is this spec with other values of them, :meth:`as_json`); the rest are
    the set-up (:func:`~sfem_filters.cardiac.measured.prepare`) and the material map the rounds
    start from. All but ``effects`` are keyword-only.

    Attributes
    ----------
    effects : tuple of str
        Catalogue effects (:data:`~sfem_filters.cardiac.effects.CATALOGUE`) of the model (a sequence
        or a comma-separated string is taken). :func:`closing_the_loop` starts from none: name the
        effects to fit with :attr:`LoopSettings.effects`.
    drive : str
        What drives the model besides its effects (:data:`~sfem_filters.cardiac.measured.DRIVES`):
        springs toward the landmarks (``"penalty"``), toward the whole contours (``"contour"``), a
        measured cavity pressure (``"pressure"``) or nothing (``"none"``); see
        :func:`~sfem_filters.cardiac.measured.build_model`.
    drive_trend : bool
        Spring targets extrapolated from the two previous frames instead of held.
    effect_rates : bool
        Effect amplitudes with rate states (integrated random walks).
    process_scale : float
        Scale of every process noise (> 0, dimensionless).
    spring_scale : float
        Scale of the drive's spring stiffness ``NOMINAL["penalty"]`` (> 0, dimensionless).
    material : str or None
        The material map (:data:`~sfem_filters.cardiac.measured.PARAMETERISATIONS`) when the rounds
        have changed it from ``parameterisation``; None: ``parameterisation``.
    parameterisation : str
        The material map the rounds start from (:data:`~sfem_filters.cardiac.measured.PARAMETERISATIONS`):
        12 regions, a smooth basis, per element, or ``"none"`` (material fixed).
    landmarks : int
        Observed landmarks per contour (endo- and epicardium, >= 3), evenly spaced in angle.
    observe : str
        :data:`~sfem_filters.cardiac.measured.OBSERVE`: the landmarks only, or also a seeded half of
        the mid-wall points.
    holdout_seed : int
        Seed of the mid-wall split (>= 0).
    mesh : str
        How the wall is meshed (:data:`~sfem_filters.cardiac.measured.MESHES`; ``"radial"``: every
        diagonal of the pixel lattice towards the cavity centre; ``"polar"``: a mesh of the wall
        apart from the points, the points observed through its shape functions).
    element_px : float
        Target element edge of ``mesh="polar"``, in the points' spacings (pixels on a pixel
        lattice; > 0).
    angle_origin_deg : float
        Where landmark 0, sector 0 of the regional map and segment 0 start: degrees about the cavity
        centre from the image's +x axis towards +y.
    """

    effects: tuple = ()
    _: KW_ONLY
    drive: str = "penalty"
    drive_trend: bool = False
    effect_rates: bool = False
    process_scale: float = 1.0
    spring_scale: float = 1.0
    material: str | None = None
    parameterisation: str = "region"
    landmarks: int = 8
    observe: str = "boundary"
    holdout_seed: int = 0
    mesh: str = "delaunay"
    element_px: float = ELEMENT_PX
    angle_origin_deg: float = 0.0

    def __post_init__(self):
        self._set("effects", _names("effects", self.effects,
                                    f"a sequence of effect names from {sorted(CATALOGUE)}"))
        _choice("drive", self.drive, DRIVES)
        self._set("drive_trend", _flag("drive_trend", self.drive_trend))
        self._set("effect_rates", _flag("effect_rates", self.effect_rates))
        self._set("process_scale", _number("process_scale", self.process_scale, positive))
        self._set("spring_scale", _number("spring_scale", self.spring_scale, positive))
        if self.material is not None:
            _choice("material", self.material, PARAMETERISATIONS)
        _choice("parameterisation", self.parameterisation, PARAMETERISATIONS)
        self._set("landmarks", integer("landmarks", self.landmarks, 3))
        _choice("observe", self.observe, OBSERVE)
        self._set("holdout_seed", integer("holdout_seed", self.holdout_seed, 0))
        _choice("mesh", self.mesh, MESHES)
        self._set("element_px", _number("element_px", self.element_px, positive, "point spacings"))
        self._set("angle_origin_deg", _finite("angle_origin_deg", self.angle_origin_deg, "degrees"))

    @property
    def material_map(self) -> str:
        """The material map the model is fitted with: ``material``, or ``parameterisation``."""
        return self.parameterisation if self.material is None else self.material

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
        """A round's model in the report's JSON (:meth:`~sfem_filters.cardiac.closing.Round.as_json`): the
        fields the rounds change, not the set-up (:meth:`to_json` has every field)."""
        return {"effects": list(self.effects), "drive": self.drive, "drive_trend": self.drive_trend,
                "effect_rates": self.effect_rates, "process_scale": self.process_scale,
                "spring_scale": self.spring_scale, "material": self.material}


@dataclass(frozen=True, kw_only=True)
class EstimatorSettings(_Spec):
    """How one model is fitted (see :func:`sfem_filters.cardiac.measured.run`).

    Attributes
    ----------
    estimator : str
        :data:`~sfem_filters.cardiac.measured.ESTIMATORS`: the iterated smoother (``"smoother"``, the
        MAP of one cycle with a Laplace posterior), the paper's cyclic joint EKF (``"cyclic"``) or the
        reduced-order UKF in the same cyclic driver (``"roukf"``).
    max_iterations : int or None
        The smoother's Gauss-Newton iteration limit (>= 1); None: the drive's default
        (:meth:`iteration_limit`, :func:`~sfem_filters.cardiac.measured.default_max_iterations`:
        20, 80 under a measured pressure). A fit stopped by its limit is reported not converged.
    max_loops : int
        Loop limit of the cyclic estimators (>= 1).
    laplace : str
        :data:`LAPLACE`: the final model's material covariance, the smoother's inverse
        Gauss-Newton Hessian (``"gauss-newton"``, free) or the inverse exact Hessian of the MAP cost
        at the final mode (``"exact"``, :func:`sfem_filters.cardiac.measured.exact_posterior`, 2 p + 1
        more gradient passes; smoother only, and a material map).
    measurement_noise : str
        :data:`~sfem_filters.filtering.iterated.NOISE_LEVELS`: ``"fixed"``, at the data's noise floor;
        ``"estimate"``, every fit's level by type-II maximum likelihood (smoother only, and the
        evidence as criterion).
    """

    estimator: str = "smoother"
    max_iterations: int | None = None
    max_loops: int = 5
    laplace: str = "gauss-newton"
    measurement_noise: str = "fixed"

    def __post_init__(self):
        _choice("estimator", self.estimator, ESTIMATORS)
        if self.max_iterations is not None:
            self._set("max_iterations", integer("max_iterations", self.max_iterations, 1))
        self._set("max_loops", integer("max_loops", self.max_loops, 1))
        _choice("laplace", self.laplace, LAPLACE)
        _choice("measurement_noise", self.measurement_noise, NOISE_LEVELS)
        if self.laplace == "exact" and self.estimator != "smoother":
            raise ValueError(f"laplace: 'exact' refines the iterated smoother's posterior; expected "
                             f"estimator='smoother', got estimator={self.estimator!r}")
        if self.measurement_noise == "estimate" and self.estimator != "smoother":
            raise ValueError(f"measurement_noise: 'estimate' needs estimator='smoother', got "
                             f"estimator={self.estimator!r}")

    def iteration_limit(self, drive: str) -> int:
        """The smoother's iteration limit for ``drive``: ``max_iterations``, or the drive's default."""
        return default_max_iterations(drive) if self.max_iterations is None else self.max_iterations


@dataclass(frozen=True, kw_only=True)
class LoopSettings(_Spec):
    """How the rounds of :func:`~sfem_filters.cardiac.closing_the_loop` search (its module
    docstring, :mod:`sfem_filters.cardiac.closing.rounds`, tells the search).

    Attributes
    ----------
    effects : "auto", "none" or tuple of str
        ``"auto"``: the rounds; ``"none"``: the baseline only; effect names (a sequence or a
        comma-separated string): the baseline and one fit with exactly those effects, no test. An
        empty sequence is ``"none"``.
    candidates : tuple of str
        The catalogue effects the rounds may add (None: :data:`DEFAULT_CANDIDATES`, the catalogue
        without :data:`~sfem_filters.cardiac.effects.EXPLICIT_ONLY`).
    max_rounds : int
        Most forward rounds, each adding an effect or a correction (>= 1; backward steps not counted).
    alpha : float
        Family-wise level of the score tests, Bonferroni-corrected over every test so far, in (0, 1).
    min_evidence : float
        Least rise of ``log p(y)`` for a candidate to be kept (nats, >= 0; ``criterion="evidence"``).
    max_tries : int
        Most significant candidates fitted per round (>= 1).
    selection : str
        :data:`SELECTIONS`: keep the best of the significant candidates fitted (``"best"``) or the
        first by score that improves the criterion (``"first"``).
    corrections : bool
        Try corrections of the drive, the noise and the material's prior when no effect passes.
    stiff_springs : str
        :data:`STIFF_SPRINGS`: which drives the correction ``springs:x10`` (springs ten times stiffer)
        is offered to. ``"contour"`` (default): only to springs spread along the whole contour
        (``drive="contour"``); on isolated landmarks stiff springs pull tents in the wall that the
        evidence can reward while the held-out error grows (the docs' validation page "Stiff springs
        only along the contours" measures both). ``"any"``: to the landmark springs of
        ``drive="penalty"`` too.
    criterion : str
        :data:`CRITERIA`: what a candidate must improve to be kept: ``log p(y)`` by more than
        ``min_evidence`` nats (``"evidence"``), or the ``folds``-fold cross-validation RMSE over the
        observed points by more than the fraction ``min_cv_gain`` of its current value (``"cv"``).
        Either way every round's model is also cross-validated and the report gives both (with the
        evidence, only when the landmarks can be split into ``folds`` folds: at most the landmarks
        per contour, leaving at least 3 per contour outside each).
    folds : int
        Folds of the cross-validation over the observed points (>= 2), reported for every round.
    min_cv_gain : float
        Least relative fall of the cross-validation RMSE (a fraction, >= 0) with ``criterion="cv"``.
    prune : bool
        After a round adds a term, take out the earlier term whose removal improves the criterion
        most, while one does (backward steps).
    warm_start : bool
        Start each fit of a round (candidates, corrections, backward steps) from the material mode
        of the model it extends or prunes instead of the prior mean (the smoother only, ignored by the
        cyclic estimators; a fit of another parameterisation starts from the prior). The MAP cost is
        the same; fewer Gauss-Newton iterations reach its stop rule.
    screen_iterations : int or None
        Screening (smoother only): every fit of a round is first made with at most this many
        Gauss-Newton iterations (>= 1) and judged by the criterion there; only the one that would be
        kept is then fitted to the full limit (from the screening fit's material with
        ``warm_start``) and kept if it still improves the criterion. None (default): every fit to
        the full limit.
    """

    effects: str | tuple = "auto"
    candidates: tuple | None = DEFAULT_CANDIDATES
    max_rounds: int = 5
    alpha: float = 0.01
    min_evidence: float = 0.0
    max_tries: int = 3
    selection: str = "best"
    corrections: bool = True
    stiff_springs: str = "contour"
    criterion: str = "evidence"
    folds: int = DEFAULT_FOLDS
    min_cv_gain: float = 0.01
    prune: bool = True
    warm_start: bool = False
    screen_iterations: int | None = None

    def __post_init__(self):
        if not (isinstance(self.effects, str) and self.effects in ("auto", "none")):
            names = _names("effects", self.effects, f"'auto', 'none' or names from {sorted(CATALOGUE)}")
            self._set("effects", names or "none")       # an empty sequence: no effect, as "none"
        self._set("candidates", DEFAULT_CANDIDATES if self.candidates is None else
                  _names("candidates", self.candidates, f"names from {sorted(CATALOGUE)}"))
        self._set("max_rounds", integer("max_rounds", self.max_rounds, 1))
        self._set("alpha", _number("alpha", self.alpha, probability))
        self._set("min_evidence", _number("min_evidence", self.min_evidence, non_negative, "nats"))
        self._set("max_tries", integer("max_tries", self.max_tries, 1))
        _choice("selection", self.selection, SELECTIONS)
        self._set("corrections", _flag("corrections", self.corrections))
        _choice("stiff_springs", self.stiff_springs, STIFF_SPRINGS)
        _choice("criterion", self.criterion, CRITERIA)
        self._set("folds", integer("folds", self.folds, 2))
        self._set("min_cv_gain", _number("min_cv_gain", self.min_cv_gain, non_negative, "(a fraction)"))
        self._set("prune", _flag("prune", self.prune))
        self._set("warm_start", _flag("warm_start", self.warm_start))
        if self.screen_iterations is not None:
            self._set("screen_iterations", integer("screen_iterations", self.screen_iterations, 1))


def check_specs(model: ModelSpec, estimator: EstimatorSettings, loop: LoopSettings) -> None:
    """Check the three specs' types and what one asks of another (a ``ValueError`` naming the field):
    the loop starts from a model without effects or a changed material map; the exact Laplace needs a
    material map; the estimated measurement noise needs the evidence as criterion; screening needs
    the smoother."""
    for name, value, cls in (("model", model, ModelSpec), ("estimator", estimator, EstimatorSettings),
                             ("loop", loop, LoopSettings)):
        if not isinstance(value, cls):
            raise TypeError(f"{name}: expected sfem_filters.cardiac.{cls.__name__}, got {type(value).__name__}")
    if model.effects:
        raise ValueError(f"model.effects: the loop starts from a model without effects; name the effects to fit "
                         f"with LoopSettings(effects=...), got {model.effects}")
    if model.material is not None:
        raise ValueError(f"model.material: set only by the rounds' corrections; choose the map with "
                         f"parameterisation, got material={model.material!r}")
    if estimator.laplace == "exact" and model.parameterisation == "none":
        raise ValueError("laplace: 'exact' needs a material map; the parameterisation is 'none' (material fixed)")
    if estimator.measurement_noise == "estimate" and loop.criterion != "evidence":
        raise ValueError(f"measurement_noise: 'estimate' needs criterion='evidence' (the cross-validation's folds "
                         f"would use the noise floor), got criterion={loop.criterion!r}")
    if loop.screen_iterations is not None and estimator.estimator != "smoother":
        raise ValueError(f"screen_iterations: screening stops the iterated smoother early; expected "
                         f"estimator='smoother', got {estimator.estimator!r}")


def specs_from(**settings) -> tuple:
    """``(ModelSpec, EstimatorSettings, LoopSettings)`` from settings named by their fields, each
    given to the spec that has it (``effects`` to :class:`LoopSettings`: what the loop fits); an
    unknown name is an error.

    >>> model, estimator, loop = specs_from(drive="contour", max_iterations=3, max_rounds=1)
    >>> model.drive, estimator.max_iterations, loop.max_rounds
    ('contour', 3, 1)
    """
    out = []
    left = dict(settings)
    for cls in (LoopSettings, EstimatorSettings, ModelSpec):
        names = {f.name for f in fields(cls)}
        out.append(cls(**{k: left.pop(k) for k in list(left) if k in names}))
    if left:
        known = sorted({f.name for cls in (ModelSpec, EstimatorSettings, LoopSettings) for f in fields(cls)})
        raise ValueError(f"settings: unknown {sorted(left)}; expected fields of the specs: {known}")
    loop, estimator, model = out
    return model, estimator, loop
