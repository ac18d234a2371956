"""Cross-validation over the observed points (issue 14): folds that partition and interleave, a
fold predicted without any of its own data, the spline's exactness on affine motion, and the
rounds' criterion."""
import functools
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from sfem_filters.cardiac import annulus_sequence, closing, measured
from sfem_filters.cardiac.specs import EstimatorSettings, LoopSettings, ModelSpec, specs_from
from sfem_filters.cardiac.crossval import cross_validate, observation_folds, spline_cross_validation
from sfem_filters.fem import Material
from sfem_filters.cardiac.reference import spline_reference


@pytest.fixture(scope="module")
def setup():
    return measured.prepare(annulus_sequence(None, n_frames=6, seed=0), 8)


@pytest.fixture(scope="module")
def nominal(setup):
    return Material.uniform(setup.mesh.n_elements, measured.NOMINAL["E"], measured.NOMINAL["nu"])


@pytest.mark.parametrize("folds", [2, 3, 4, 5])
def test_folds_partition_the_observed_points_and_interleave_along_each_contour(setup, folds):
    parts = observation_folds(setup, folds)
    assert len(parts) == folds
    allp = np.concatenate(parts)
    assert len(allp) == len(setup.observed) and set(allp) == set(setup.observed)
    fold_of = {p: f for f, part in enumerate(parts) for p in part}
    n = setup.n_landmarks
    for contour in (setup.landmarks[:n], setup.landmarks[n:]):
        # neighbours along a contour (angle order) are never in the same fold
        for a, b in zip(contour, np.roll(contour, -1)):
            if n % folds == 0 or b != contour[0]:
                assert fold_of[a] != fold_of[b]
        assert all(np.sum(~np.isin(contour, part)) >= 3 for part in parts)


def test_midwall_points_are_dealt_to_the_folds():
    su = measured.prepare(annulus_sequence(None, n_frames=6, seed=0), 8, observe="boundary+midwall")
    parts = observation_folds(su, 4)
    other = np.setdiff1d(su.observed, su.landmarks)
    counts = [np.isin(part, other).sum() for part in parts]
    assert sum(counts) == len(other) and max(counts) - min(counts) <= 1


def test_bad_folds_are_rejected(setup, nominal):
    with pytest.raises(ValueError, match="folds"):
        observation_folds(setup, 1)
    su4 = measured.prepare(annulus_sequence(None, n_frames=6, seed=0), 4)
    with pytest.raises(ValueError, match="at least 4 folds"):
        observation_folds(su4, 2)                       # 2 of 4 landmarks left per contour
    assert len(observation_folds(su4, 4)) == 4          # one left out of 4: 3 stay
    with pytest.raises(ValueError, match="at most 8"):
        observation_folds(setup, 10)                    # folds without a landmark
    with pytest.raises(ValueError, match="material"):
        cross_validate(setup, None)
    with pytest.raises(ValueError, match="material"):
        cross_validate(setup, nominal, parameterisation="region")
    seq = annulus_sequence(None, n_frames=4, seed=0)
    for kw, match in (({"criterion": "aic"}, "criterion"), ({"folds": 1}, "folds"), ({"min_cv_gain": -0.1}, "min_cv_gain"),
                      ({"criterion": "cv", "landmarks": 4, "folds": 2}, "at least 4 folds")):
        with pytest.raises(ValueError, match=match):
            closing.closing_the_loop(seq, *specs_from(**kw))


@pytest.mark.parametrize("drive", ["penalty", "contour"])
def test_a_fold_is_predicted_without_any_of_its_own_data(setup, nominal, drive):
    """Changing the data of a fold's points leaves the fold's predictions exactly as they were
    (its points neither drive nor are observed, nor set a noise level); changing another
    observed point's data moves them."""
    data = np.array(setup.seq.displacement)
    base = cross_validate(setup, nominal, drive=drive, folds=2, drive_trend=True)
    fold0 = np.asarray(base["folds"][0])
    k = len(fold0)
    rng = np.random.default_rng(3)
    moved = data.copy()
    moved[:, fold0] += rng.standard_normal(moved[:, fold0].shape) * 0.5
    again = cross_validate(replace(setup, obs_displacement=moved), nominal, drive=drive, folds=2, drive_trend=True)
    np.testing.assert_allclose(again["U"][:, :k], base["U"][:, :k], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(again["U_residual_spline"][:, :k], base["U_residual_spline"][:, :k], rtol=1e-9,
                               atol=1e-12)                                 # the residual's spline does not see it
    other = np.asarray(base["folds"][1])[0]
    moved = data.copy()
    moved[:, other] += 0.5
    again = cross_validate(replace(setup, obs_displacement=moved), nominal, drive=drive, folds=2, drive_trend=True)
    assert np.max(np.abs(again["U"][:, :k] - base["U"][:, :k])) > 1e-3
    assert np.max(np.abs(again["U_residual_spline"][:, :k] - base["U_residual_spline"][:, :k])) > 1e-3
    # and the error is that of the predictions against the data, over every fold's points
    r = data[:, base["points"]] - base["U"]
    assert np.isclose(base["rmse_px"], np.sqrt(np.nanmean(np.sum(r ** 2, axis=2))))
    assert np.isclose(base["rmse_px"] ** 2, base["rmse_radial_px"] ** 2 + base["rmse_circumferential_px"] ** 2)


@functools.lru_cache(maxsize=1)
def _three_frames():
    return measured.prepare(annulus_sequence(None, n_frames=3, seed=0), 8)


@settings(max_examples=6, deadline=None)
@given(st.integers(0, 2 ** 31 - 1), st.integers(2, 4))
def test_spline_cross_validation_is_exact_on_affine_motion(seed, folds):
    """A thin-plate spline reproduces an affine field exactly, so its cross-validation error is
    round-off; the folds are those of :func:`observation_folds`."""
    su = _three_frames()
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((3, 2, 2)) * 0.05
    c = rng.standard_normal((3, 2))
    disp = np.einsum("fij,pj->fpi", A, su.seq.points) + c[:, None]
    cv = spline_cross_validation(replace(su, obs_displacement=disp), folds)
    assert cv["rmse_px"] < 1e-8
    assert [sorted(f) for f in cv["folds"]] == [sorted(f) for f in
                                                (p.tolist() for p in observation_folds(su, folds))]


def test_the_model_cross_validates_better_than_the_wrong_drive(setup, nominal):
    """On a sequence drawn from the penalty-driven model, the model it was drawn from predicts the
    left-out landmarks better than the same model with no drive at all."""
    right = cross_validate(setup, nominal, drive="penalty", folds=2)
    wrong = cross_validate(setup, nominal, drive="none", folds=2)
    assert right["rmse_px"] < 0.75 * wrong["rmse_px"]


def test_rounds_judged_by_cross_validation_keep_what_lowers_it():
    """With ``criterion="cv"`` a candidate passes when it lowers the cross-validation error by more
    than ``min_cv_gain`` of it, and the round keeps the passing one with the largest fall (the
    default ``selection="best"``); every round and the spline carry their CV, and the report
    prints it."""
    seq = annulus_sequence("active_polar", n_frames=8, seed=1)
    out = closing.closing_the_loop(seq, ModelSpec(parameterisation="none"), EstimatorSettings(max_iterations=3),
                                   LoopSettings(criterion="cv", folds=2, candidates=["active_polar", "cavity_pressure"],
                                                max_rounds=1, corrections=False, min_cv_gain=0.01))
    js = out.as_json()
    assert js["config"]["criterion"] == "cv"
    assert all(r["cross_validation"]["rmse_px"] > 0 for r in js["rounds"])
    assert js["spline_reference"]["cross_validation"]["rmse_px"] > 0
    tried = js["rounds"][-1]["tried"] if len(js["rounds"]) > 1 else js["last_attempt"]["tried"]
    assert tried, "the uniform active stress is significant on its own sequence"
    cv0 = js["rounds"][0]["cross_validation"]["rmse_px"]
    for t in tried:
        assert np.isclose(t["cv_gain_px"], cv0 - t["cv_rmse_px"])
    passing = [t for t in tried if t["cv_gain_px"] > 0.01 * cv0]
    kept = [t for t in tried if t["accepted"]]
    assert len(kept) == (1 if passing else 0)
    if passing:
        assert kept[0]["cv_gain_px"] == max(t["cv_gain_px"] for t in passing)
    if len(js["rounds"]) > 1:
        assert np.isclose(js["rounds"][1]["cross_validation"]["rmse_px"], tried[-1]["cv_rmse_px"])
    report = closing.format_report(out)
    assert "cross-validation" in report and "CV" in report
    # every round's model plus the spline of its residual, held out and cross-validated
    for r in js["rounds"]:
        assert r["residual_spline"]["heldout_rmse_px"] > 0 and r["cross_validation"]["residual_spline"]["rmse_px"] > 0
    assert "+spline" in report and f"{js['rounds'][-1]['residual_spline']['heldout_rmse_px']:.3f}" in report


def test_a_folds_own_velocities_are_left_out_too(setup, nominal):
    """Velocity data at observed points (image-derived fusion) leave a fold with its
    displacements: changing a fold's velocities does not move its predictions."""
    F = setup.seq.n_frames
    rng = np.random.default_rng(5)
    vel = rng.standard_normal((F, len(setup.landmarks), 2)) * 2.0
    su = replace(setup, velocity_points=setup.landmarks, velocity=vel, velocity_sigma=np.full((F, len(setup.landmarks)), 1.0))
    base = cross_validate(su, nominal, folds=2)
    fold0 = np.asarray(base["folds"][0])
    k = len(fold0)
    moved = vel.copy()
    moved[:, np.isin(setup.landmarks, fold0)] += 5.0
    again = cross_validate(replace(su, velocity=moved), nominal, folds=2)
    np.testing.assert_allclose(again["U"][:, :k], base["U"][:, :k], rtol=1e-9, atol=1e-12)


def test_a_candidate_that_raises_the_cv_error_is_rejected(monkeypatch):
    """Under ``criterion="cv"`` the decision is the CV error's, not the evidence's: a significant
    effect whose model cross-validates worse is fitted, rejected, and the rounds stop with "cv"."""
    real = closing.round_cross_validation

    def worse_with_effects(setup, variant, r, folds=4):
        cv = real(setup, variant, r, folds)
        return {**cv, "rmse_px": cv["rmse_px"] * (10.0 if variant.effects else 1.0)}

    for part in (closing.rounds, closing.workers):      # where it is looked up
        monkeypatch.setattr(part, "round_cross_validation", worse_with_effects)
    seq = annulus_sequence("active_polar", n_frames=8, seed=1)
    out = closing.closing_the_loop(seq, ModelSpec(parameterisation="none"), EstimatorSettings(max_iterations=3),
                                   LoopSettings(criterion="cv", folds=2, candidates=["active_polar"], max_rounds=1,
                                                corrections=False))
    assert out.effects == [] and out.stop_reason == "cv"
    (t,) = out.last_attempt["tried"]
    assert t["effect"] == "active_polar" and not t["accepted"] and t["evidence_gain"] > 0 and t["cv_gain_px"] < 0


def test_a_runs_report_gives_the_model_plus_the_spline_of_its_residual(setup):
    """The run's ``residual_spline`` is the spline of its observed residual added to its held-out
    prediction, scored like the model; and the cross-validation reports the same for every fold."""
    r = measured.run(setup, (), "contour", "none", drive_trend=True)
    seq, h = setup.seq, setup.heldout
    nodes = setup.node_of_point[h]
    res = spline_reference(seq.points, seq.displacement - r.U, setup.observed, h, setup.geometry.radial[nodes],
                           setup.geometry.circumferential[nodes])
    pred = r.U[:, h] + res["U"]
    expected = np.sqrt(np.nanmean(np.sum((seq.displacement[:, h] - pred) ** 2, axis=2)))
    assert r.metrics["residual_spline"]["heldout_rmse_px"] == pytest.approx(expected, rel=1e-10)
    assert r.metrics["residual_spline"]["heldout_rmse_px"] != pytest.approx(r.metrics["heldout_rmse_px"], rel=1e-3)
    cv = closing.round_cross_validation(setup, ModelSpec(drive="contour", drive_trend=True), r, 2)
    assert set(cv["residual_spline"]) == {"rmse_px", "rmse_radial_px", "rmse_circumferential_px", "per_fold_px"}
    assert np.isfinite(cv["residual_spline"]["rmse_px"]) and cv["residual_spline"]["rmse_px"] != cv["rmse_px"]


def test_the_residual_spline_uses_the_data_the_model_saw_and_scores_against_the_measured(setup):
    """With observations that differ from the measured displacement (tracked borders, say), the
    residual's spline is fitted to what the model observed, and the held-out points are scored
    against the measured displacement: moving the observed data moves the corrected prediction,
    moving the held-out points' observation data does not."""
    seq, h, o = setup.seq, setup.heldout, setup.observed
    rng = np.random.default_rng(7)
    seen = np.array(seq.displacement)
    seen[:, o] += rng.standard_normal(seen[:, o].shape) * 0.2
    r = measured.run(replace(setup, obs_displacement=seen), (), "contour", "none", drive_trend=True)
    nodes = setup.node_of_point[h]
    dirs = setup.geometry.radial[nodes], setup.geometry.circumferential[nodes]
    corr = spline_reference(seq.points, seen - r.U, o, h, *dirs)["U"]
    expected = np.sqrt(np.nanmean(np.sum((seq.displacement[:, h] - r.U[:, h] - corr) ** 2, axis=2)))
    assert r.metrics["residual_spline"]["heldout_rmse_px"] == pytest.approx(expected, rel=1e-10)
    wrong = spline_reference(seq.points, seq.displacement - r.U, o, h, *dirs)["U"]
    assert not np.allclose(corr, wrong)
    junk = np.array(seen)
    junk[:, h] += 5.0                                   # the held-out points' observation data: unused
    again = measured.run(replace(setup, obs_displacement=junk), (), "contour", "none", drive_trend=True)
    assert again.metrics["residual_spline"]["heldout_rmse_px"] == pytest.approx(expected, rel=1e-9)
