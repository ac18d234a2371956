"""The settings specs of closing the loop (issue 40 item 5): every field checked when a spec is made
(a ValueError naming the field), a JSON round trip, settings sorted to their specs, and
closing_the_loop refusing what is not a spec, or specs that ask something of each other they
cannot have, before any fit."""
import dataclasses
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.cardiac import CATALOGUE, annulus_sequence, closing, closing_the_loop
from sfem_filters.cardiac.measured import DRIVES, ESTIMATORS, MESHES, OBSERVE, PARAMETERISATIONS
from sfem_filters.cardiac.specs import (CRITERIA, DEFAULT_CANDIDATES, LAPLACE, SELECTIONS, STIFF_SPRINGS,
                                        EstimatorSettings, LoopSettings, ModelSpec, check_specs, specs_from)
from sfem_filters.filtering.iterated import NOISE_LEVELS

NAMES = st.lists(st.sampled_from(sorted(CATALOGUE)), max_size=3, unique=True).map(tuple)
FACTOR = st.floats(1e-3, 1e3)

MODELS = st.builds(ModelSpec, NAMES, drive=st.sampled_from(DRIVES), drive_trend=st.booleans(),
                   effect_rates=st.booleans(), process_scale=FACTOR, spring_scale=FACTOR,
                   material=st.none() | st.sampled_from(PARAMETERISATIONS),
                   parameterisation=st.sampled_from(PARAMETERISATIONS), landmarks=st.integers(3, 64),
                   observe=st.sampled_from(OBSERVE), holdout_seed=st.integers(0, 2 ** 31),
                   mesh=st.sampled_from(MESHES), element_px=st.floats(0.1, 10.0),
                   angle_origin_deg=st.floats(-360.0, 360.0))
ESTIMATOR_SETTINGS = st.builds(EstimatorSettings, estimator=st.just("smoother"),
                               max_iterations=st.none() | st.integers(1, 200), max_loops=st.integers(1, 50),
                               laplace=st.sampled_from(LAPLACE), measurement_noise=st.sampled_from(NOISE_LEVELS)) | \
    st.builds(EstimatorSettings, estimator=st.sampled_from(ESTIMATORS[1:]), max_loops=st.integers(1, 50))
LOOPS = st.builds(LoopSettings, effects=st.sampled_from(["auto", "none"]) | NAMES.filter(bool),
                  candidates=NAMES, max_rounds=st.integers(1, 9), alpha=st.floats(1e-6, 0.5),
                  min_evidence=st.floats(0.0, 50.0), max_tries=st.integers(1, 9),
                  selection=st.sampled_from(SELECTIONS), corrections=st.booleans(),
                  stiff_springs=st.sampled_from(STIFF_SPRINGS), criterion=st.sampled_from(CRITERIA),
                  folds=st.integers(2, 9), min_cv_gain=st.floats(0.0, 1.0), prune=st.booleans(),
                  warm_start=st.booleans(), screen_iterations=st.none() | st.integers(1, 9))


@settings(max_examples=60, deadline=None)
@given(spec=MODELS | ESTIMATOR_SETTINGS | LOOPS)
def test_every_spec_survives_its_json_round_trip(spec):
    """``to_json`` holds every field as JSON values (through a JSON text and back), ``from_json``
    makes the same spec, and a spec is a value: equal specs hash alike."""
    js = json.loads(json.dumps(spec.to_json(), allow_nan=False))
    assert set(js) == {f.name for f in dataclasses.fields(spec)}
    back = type(spec).from_json(js)
    assert back == spec and hash(back) == hash(spec)
    assert type(spec).from_json({}) == type(spec)()          # a field left out takes its default


#: A bad value of every field of every spec, and what the message must say of it
BAD = {
    ModelSpec: {"effects": (["glue"], "effects: expected a sequence of effect names"),
                "drive": ("springs", "drive: expected one of"), "drive_trend": ("yes", "drive_trend: expected True"),
                "effect_rates": (1, "effect_rates: expected True"),
                "process_scale": (0.0, "process_scale: expected a positive"),
                "spring_scale": ("ten", "spring_scale: expected a positive"),
                "material": ("smooth", "material: expected one of"),
                "parameterisation": ("regions", "parameterisation: expected one of"),
                "landmarks": (2, "landmarks: expected an integer >= 3"),
                "observe": ("midwall", "observe: expected one of"),
                "holdout_seed": (-1, "holdout_seed: expected an integer >= 0"),
                "mesh": ("lattice", "mesh: expected one of"),
                "element_px": (-2.0, "element_px: expected a positive finite number in point spacings"),
                "angle_origin_deg": (np.nan, "angle_origin_deg: expected a finite number in degrees")},
    EstimatorSettings: {"estimator": ("ekf", "estimator: expected one of"),
                        "max_iterations": (0, "max_iterations: expected an integer >= 1"),
                        "max_loops": (2.5, "max_loops: expected an integer >= 1"),
                        "laplace": ("newton", "laplace: expected one of"),
                        "measurement_noise": ("auto", "measurement_noise: expected one of")},
    LoopSettings: {"effects": ("auto,glue", "effects: expected 'auto', 'none' or names from"),
                   "candidates": (["nope"], "candidates: expected names from"),
                   "max_rounds": (0, "max_rounds: expected an integer >= 1"),
                   "alpha": (1.5, "alpha: expected a number in the open interval"),
                   "min_evidence": (-1.0, "min_evidence: expected a non-negative finite number in nats"),
                   "max_tries": (True, "max_tries: expected an integer >= 1"),
                   "selection": ("greedy", "selection: expected one of"),
                   "corrections": ("no", "corrections: expected True"),
                   "stiff_springs": ("landmarks", "stiff_springs: expected one of"),
                   "criterion": ("aic", "criterion: expected one of"),
                   "folds": (1, "folds: expected an integer >= 2"),
                   "min_cv_gain": (np.inf, "min_cv_gain: expected a non-negative"),
                   "prune": ("yes", "prune: expected True"), "warm_start": (None, "warm_start: expected True"),
                   "screen_iterations": (0, "screen_iterations: expected an integer >= 1")},
}


@pytest.mark.parametrize("cls", list(BAD))
def test_every_bad_value_is_a_value_error_naming_the_field(cls):
    assert set(BAD[cls]) == {f.name for f in dataclasses.fields(cls)}     # every field has its case
    for name, (value, message) in BAD[cls].items():
        with pytest.raises(ValueError, match="^" + message.replace("(", r"\(")):
            cls(**{name: value})
        with pytest.raises(ValueError, match=f"^{name}: "):                 # also when changed
            cls().with_(**{name: value})
    with pytest.raises(ValueError, match="unknown fields"):
        cls.from_json({"colour": "blue"})
    with pytest.raises(TypeError):
        cls(colour="blue")


def test_the_estimators_own_combinations_are_checked():
    with pytest.raises(ValueError, match="^laplace: 'exact' .* estimator='smoother'"):
        EstimatorSettings(estimator="cyclic", laplace="exact")
    with pytest.raises(ValueError, match="^measurement_noise: 'estimate' needs estimator='smoother'"):
        EstimatorSettings(estimator="roukf", measurement_noise="estimate")


def test_values_are_normalised_when_made():
    """Names from a comma list or any sequence become a tuple, an empty one is "none", no candidates
    given are the default ones, and numbers of numpy types become Python's (the JSON is plain)."""
    loop = LoopSettings(effects="active_polar, cavity_pressure", candidates=None, folds=np.int64(3),
                        alpha=np.float32(0.25), prune=np.bool_(False))
    assert loop.effects == ("active_polar", "cavity_pressure") and loop.candidates == DEFAULT_CANDIDATES
    assert LoopSettings(effects=[]).effects == "none" and LoopSettings(effects=()).effects == "none"
    assert type(loop.folds) is int and type(loop.alpha) is float and loop.prune is False
    assert ModelSpec("active_polar").effects == ("active_polar",)     # one name, not its letters
    assert ModelSpec(landmarks=np.int32(6)).landmarks == 6 and type(ModelSpec(spring_scale=10).spring_scale) is float


def test_settings_go_to_the_spec_that_has_them():
    model, estimator, loop = specs_from(effects="none", drive="contour", mesh="polar", max_iterations=4,
                                        criterion="cv", warm_start=True)
    assert model == ModelSpec(drive="contour", mesh="polar")
    assert estimator == EstimatorSettings(max_iterations=4)
    assert loop == LoopSettings(effects="none", criterion="cv", warm_start=True)
    assert specs_from() == (ModelSpec(), EstimatorSettings(), LoopSettings())
    with pytest.raises(ValueError, match=r"^settings: unknown \['meshes'\]"):
        specs_from(meshes="polar")
    every = [f.name for cls in (ModelSpec, EstimatorSettings, LoopSettings) for f in dataclasses.fields(cls)]
    assert len(every) - len(set(every)) == 1        # one name in two specs: effects, the loop's in specs_from


def test_a_rounds_model_is_the_spec_with_its_changes_and_its_report_columns_are_unchanged():
    """The rounds' model columns in a report (``as_json``) and its label are the former ``Variant``'s;
    the material map the fit uses is the rounds' change, or the configured map."""
    v = ModelSpec(("active_segments",), effect_rates=True, spring_scale=10.0, parameterisation="element")
    assert v.label("penalty") == "active_segments [effect trend] [springs x10]"
    assert list(v.as_json()) == ["effects", "drive", "drive_trend", "effect_rates", "process_scale", "spring_scale",
                                 "material"]
    assert v.material_map == "element" and v.with_(material="basis").material_map == "basis"
    assert closing._variant(v.as_json()) == v.with_(parameterisation="region")    # the set-up is not a column


def test_closing_the_loop_refuses_what_is_not_a_spec_before_any_fit(monkeypatch):
    seq = annulus_sequence(None, n_frames=4, seed=0)
    fits = []
    monkeypatch.setattr(closing.rounds, "_fit", lambda *a, **k: fits.append(a) or pytest.fail("fitted"))
    with pytest.raises(TypeError, match="unexpected keyword argument 'alpha'"):
        closing_the_loop(seq, alpha=0.05)
    for args, match in ((({"drive": "contour"},), "model: expected sfem_filters.cardiac.ModelSpec, got dict"),
                        ((ModelSpec(), LoopSettings()), "estimator: expected sfem_filters.cardiac.EstimatorSettings"),
                        ((ModelSpec(), EstimatorSettings(), "auto"), "loop: expected sfem_filters.cardiac.LoopSettings, got str")):
        with pytest.raises(TypeError, match=match):
            closing_the_loop(seq, *args)
    for specs, match in (((ModelSpec(("active_polar",)),), "^model.effects: the loop starts from a model"),
                         ((ModelSpec(material="basis"),), "^model.material: set only by the rounds"),
                         ((ModelSpec(parameterisation="none"), EstimatorSettings(laplace="exact")),
                          "^laplace: 'exact' needs a material map"),
                         ((ModelSpec(), EstimatorSettings(measurement_noise="estimate"), LoopSettings(criterion="cv")),
                          "^measurement_noise: 'estimate' needs criterion='evidence'"),
                         ((ModelSpec(), EstimatorSettings(estimator="cyclic"), LoopSettings(screen_iterations=2)),
                          "^screen_iterations: screening stops the iterated smoother early")):
        with pytest.raises(ValueError, match=match):
            closing_the_loop(seq, *specs)
        with pytest.raises(ValueError, match=match):
            check_specs(*specs, *[EstimatorSettings(), LoopSettings()][len(specs) - 1:])
    with pytest.raises(ValueError, match="workers"):
        closing_the_loop(seq, workers=0)
    assert fits == []
