"""The process and measurement noise levels estimated by maximum evidence
(``IteratedSmoother(process_noise="estimate")``, ``measurement_noise="estimate"``)."""
import re
import warnings

import numpy as np
import pytest
from helpers import BiasModel
from hypothesis import example, given, settings
from hypothesis import strategies as st

from sfem_filters.benchmark.calibration import pinned_problem
from sfem_filters.filtering import IteratedSmoother, scaled_measurement_noise, scaled_process_noise
from sfem_filters.filtering.linear import LinearGaussianModel


def _data(rng, n, p, m, frames, q_true_factor, r_true_factor=1.0):
    """A random stable BiasModel (linear in x and theta: its evidence is exact) and data whose
    process noise is ``q_true_factor`` times the model's, measurement noise ``r_true_factor``."""
    A = rng.standard_normal((n, n))
    A *= 0.9 / max(abs(np.linalg.eigvals(A)))
    G = 0.3 * rng.standard_normal((n, p))
    H = rng.standard_normal((m, n))
    Q = np.diag(rng.uniform(0.01, 0.1, n))
    R = np.diag(rng.uniform(0.01, 0.05, m))
    model = BiasModel(A, G, H, Q, R, 0.1 * np.eye(n), np.eye(p), frames, np.zeros(p))
    theta = rng.standard_normal(p)
    x, y = np.zeros(n), np.empty((frames, m))
    for t in range(frames):
        if t:
            x = A @ x + G @ theta + rng.multivariate_normal(np.zeros(n), q_true_factor * Q)
        y[t] = H @ x + rng.multivariate_normal(np.zeros(m), r_true_factor * R)
    return model, y


def _assert_same_result(est, fixed):
    """An estimated level's result is the fixed-level run at that level: material, its covariance
    and the evidence."""
    np.testing.assert_allclose(est.theta, fixed.theta, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(est.P_theta, fixed.P_theta, rtol=1e-6)
    np.testing.assert_allclose(est.log_likelihood, fixed.log_likelihood, rtol=1e-10)


@pytest.mark.filterwarnings("ignore:filter inconsistent")
@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), log4_factor=st.sampled_from([-3.0, -1.0, 0.0, 1.0, 2.0]))
@example(seed=144613, log4_factor=2.0)   # once overflowed Nielsen's damping factor (vanishing predicted decrease)
def test_estimated_level_is_the_evidence_maximum_and_near_the_truth(seed, log4_factor):
    """Linear model, long sequence: the chosen factor is within 0.05 nats (noise_tol) of the best
    evidence over the whole grid of factors 4^k, recomputed with fixed-Q runs, and within a factor
    of 4 of the factor the data were made with; the result is the fixed-Q run at that factor
    (undamped: for a linear model one Gauss-Newton step is exact, from any start)."""
    rng = np.random.default_rng(seed)
    model, y = _data(rng, 3, 2, 2, 120, 4.0 ** log4_factor)
    est = IteratedSmoother(process_noise="estimate", damping=0.0).run(model, y)
    only_evidence = IteratedSmoother(damping=0.0, covariance=False)
    grid = {k: only_evidence.run(model.with_process_noise(4.0 ** k), y).log_likelihood
            for k in range(-6, 4)}
    chosen = max(d["log_evidence"] for d in est.noise_search)
    assert chosen >= max(grid.values()) - 0.05
    assert est.noise_search == sorted(est.noise_search, key=lambda d: d["scale"])
    assert {d["scale"] for d in est.noise_search} >= {1.0}
    if log4_factor > -3.0:             # a smaller true Q than 4^-3 is hidden by R at this length
        assert abs(np.log(est.process_noise_scale) / np.log(4.0) - log4_factor) <= 1.0
    fixed = IteratedSmoother(damping=0.0).run(model.with_process_noise(est.process_noise_scale), y)
    _assert_same_result(est, fixed)


@pytest.mark.filterwarnings("ignore:filter inconsistent")
@settings(max_examples=3, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), log4_factor=st.sampled_from([-2.0, -1.0, 0.0, 1.0, 2.0]))
def test_estimated_measurement_level_is_the_evidence_maximum_and_near_the_truth(seed, log4_factor):
    """As for Q: the factor on R chosen is within noise_tol of the best evidence over the grid of
    factors 4^k (fixed-R runs), within a factor of 4 of the factor the data were made with, and the
    result is the fixed-R run at that factor."""
    rng = np.random.default_rng(seed)
    model, y = _data(rng, 3, 2, 4, 150, 1.0, 4.0 ** log4_factor)
    est = IteratedSmoother(measurement_noise="estimate", damping=0.0).run(model, y)
    only_evidence = IteratedSmoother(damping=0.0, covariance=False)
    grid = {k: only_evidence.run(model.with_measurement_noise(4.0 ** k), y).log_likelihood
            for k in range(-5, 5)}
    assert max(d["log_evidence"] for d in est.measurement_noise_search) >= max(grid.values()) - 0.05
    assert est.process_noise_scale == 1.0 and est.noise_search == []
    assert abs(np.log(est.measurement_noise_scale) / np.log(4.0) - log4_factor) <= 1.0
    fixed = IteratedSmoother(damping=0.0).run(model.with_measurement_noise(est.measurement_noise_scale), y)
    _assert_same_result(est, fixed)


@pytest.mark.filterwarnings("ignore:filter inconsistent")
def test_both_levels_estimated_in_turn_never_lose_evidence_and_find_both():
    """Data made with R x 16 and Q x 1/16: estimating R alone, then R and Q in turn (Q's walk starts
    at the R-only mode), the evidence does not fall, and both factors land within 4x of the truth."""
    rng = np.random.default_rng(3)
    model, y = _data(rng, 3, 2, 4, 200, 4.0 ** -2, 4.0 ** 2)
    r_only = IteratedSmoother(measurement_noise="estimate", damping=0.0).run(model, y)
    both = IteratedSmoother(measurement_noise="estimate", process_noise="estimate", damping=0.0).run(model, y)
    assert both.log_likelihood >= r_only.log_likelihood - 1e-9
    assert both.measurement_noise_scale == r_only.measurement_noise_scale
    assert both.measurement_noise_search == r_only.measurement_noise_search and both.noise_search
    assert abs(np.log(both.measurement_noise_scale) / np.log(4.0) - 2.0) <= 1.0
    assert abs(np.log(both.process_noise_scale) / np.log(4.0) + 2.0) <= 1.0
    fixed = IteratedSmoother(damping=0.0).run(model.with_measurement_noise(both.measurement_noise_scale)
                                              .with_process_noise(both.process_noise_scale), y)
    np.testing.assert_allclose(both.log_likelihood, fixed.log_likelihood, rtol=1e-10)


def test_with_measurement_noise_scales_r_only_and_changes_the_fingerprint():
    model, _, _, _ = pinned_problem(0)
    other = scaled_measurement_noise(model, 4.0)
    np.testing.assert_array_equal(other.R, 4.0 * model.R)
    np.testing.assert_array_equal(other.Q, model.Q)
    assert other.fingerprint() != model.fingerprint()
    z = np.tile(model.x0, (model.n_frames, 1))
    np.testing.assert_allclose(other.linearise(z).R, 4.0 * model.linearise(z).R, rtol=1e-12)
    np.testing.assert_allclose(other.linearise(z).Q, model.linearise(z).Q, rtol=1e-12)


def test_pinned_noise_free_truth_gets_a_smaller_q_and_a_tighter_posterior():
    """The calibration spec's truth moves without process noise: the evidence lowers the pinned
    configuration's Q, and the material posterior tightens with it (spread, not location)."""
    model, y, theta_true, _ = pinned_problem(0)
    fixed = IteratedSmoother().run(model, y)
    est = IteratedSmoother(process_noise="estimate").run(model, y)
    assert est.process_noise_scale < 1.0
    assert est.log_likelihood > fixed.log_likelihood + 1.0
    assert np.all(np.linalg.eigvalsh(fixed.P_theta - est.P_theta) > -1e-12)
    assert est.converged and all(d["converged"] for d in est.noise_search)
    assert np.all(np.isfinite(est.output_sd["strain"]))


def test_with_process_noise_scales_q_only_and_changes_the_fingerprint():
    model, _, _, _ = pinned_problem(0)
    before = model.Q.copy()
    other = scaled_process_noise(model, 0.25)
    np.testing.assert_array_equal(other.Q, 0.25 * before)
    np.testing.assert_array_equal(model.Q, before)
    np.testing.assert_array_equal(other.P0, model.P0)
    assert other.fingerprint() != model.fingerprint()
    assert model.with_process_noise(1.0).fingerprint() == model.fingerprint()
    z = np.tile(model.x0, (model.n_frames, 1))
    np.testing.assert_allclose(other.linearise(z).Q, 0.25 * model.linearise(z).Q, rtol=1e-12)
    with pytest.raises(ValueError, match="scale: expected a positive"):
        model.with_process_noise(0.0)


class _NoScale(LinearGaussianModel):
    with_process_noise = None
    with_measurement_noise = None


def test_estimate_needs_a_scalable_model_and_sane_settings():
    m = LinearGaussianModel(np.eye(1), np.eye(1), np.eye(1), np.eye(1), [0.0], np.eye(1), 3)
    bare = _NoScale(np.eye(1), np.eye(1), np.eye(1), np.eye(1), [0.0], np.eye(1), 3)
    IteratedSmoother(process_noise="estimate").run(m, np.zeros((3, 1)))
    with pytest.raises(TypeError, match="model: estimating the process noise level needs"):
        IteratedSmoother(process_noise="estimate").run(bare, np.zeros((3, 1)))
    with pytest.raises(TypeError, match="model: estimating the measurement noise level needs"):
        IteratedSmoother(measurement_noise="estimate").run(bare, np.zeros((3, 1)))
    for kwargs, match in [(dict(process_noise="auto"), "process_noise: expected 'fixed' or 'estimate'"),
                          (dict(measurement_noise="auto"), "measurement_noise: expected 'fixed' or 'estimate'"),
                          (dict(noise_range=(2.0, 4.0)), "noise_range: expected 0 < low <= 1 <= high"),
                          (dict(noise_range=3.0), "noise_range: expected two factors"),
                          (dict(noise_tol=0.0), "noise_tol: expected a positive")]:
        with pytest.raises(ValueError, match=match):
            IteratedSmoother(**kwargs)


@pytest.mark.filterwarnings("ignore:filter inconsistent")
def test_a_level_at_the_end_of_the_range_is_warned_about_and_one_inside_is_not():
    """Data made with 16 times the model's Q: a range that stops at 4 leaves the evidence's best at its
    end (the search cannot see beyond it) and says so; a range that holds 16 finds it without a word."""
    rng = np.random.default_rng(5)
    model, y = _data(rng, 3, 2, 2, 120, 16.0)
    with pytest.warns(RuntimeWarning, match=r"highest at the end of noise_range \(Q x 4;.*widen noise_range") as rec:
        short = IteratedSmoother(process_noise="estimate", damping=0.0, noise_range=(4.0 ** -2, 4.0)).run(model, y)
    assert short.process_noise_scale == 4.0
    assert any(w.filename == __file__ for w in rec if "noise_range" in str(w.message))    # points at the caller
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        warnings.filterwarnings("ignore", "filter inconsistent")
        wide = IteratedSmoother(process_noise="estimate", damping=0.0).run(model, y)
    assert 4.0 < wide.process_noise_scale < 4.0 ** 3


def test_only_the_chosen_levels_warnings_are_shown(monkeypatch):
    """Each level tried warns (a stand-in for a filter's NIS warning); the user sees the chosen level's
    warning alone, once, saying which level it is, not one per level tried."""
    model, y = _data(np.random.default_rng(3), 3, 2, 2, 40, 16.0)
    fit = IteratedSmoother._fit

    def warning_fit(self, model, observations, **kwargs):
        warnings.warn(f"trial warning from {kwargs['description']}", RuntimeWarning)
        return fit(self, model, observations, **kwargs)
    monkeypatch.setattr(IteratedSmoother, "_fit", warning_fit)
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        est = IteratedSmoother(process_noise="estimate", covariance=False).run(model, y, description="run")
    assert len(est.noise_search) >= 3
    texts = [str(w.message) for w in shown if "trial warning" in str(w.message)]
    scale = f"{est.process_noise_scale:.3g}"
    assert texts == [f"trial warning from run (Q x {scale}) (run, at the process noise level chosen: Q x {scale})"]


def test_the_chosen_levels_warnings_keep_their_module_and_a_failing_levels_are_shown(monkeypatch):
    """A filter by module still silences the re-shown warnings (they come from where they first
    came); a level whose run fails shows its own warnings before the error goes on."""
    model, y = _data(np.random.default_rng(3), 3, 2, 2, 40, 16.0)
    fit = IteratedSmoother._fit
    calls = []

    def warning_fit(self, model, observations, **kwargs):
        calls.append(kwargs["description"])
        warnings.warn(f"trial warning from {kwargs['description']}", RuntimeWarning)
        if failing and len(calls) == 2:
            raise FloatingPointError("the second level failed")
        return fit(self, model, observations, **kwargs)
    monkeypatch.setattr(IteratedSmoother, "_fit", warning_fit)
    failing = False
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        warnings.filterwarnings("ignore", module=re.escape(__name__))
        IteratedSmoother(process_noise="estimate", covariance=False).run(model, y, description="run")
    assert not [w for w in shown if "trial warning" in str(w.message)]
    failing, calls[:] = True, []
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        with pytest.raises(FloatingPointError, match="the second level failed"):
            IteratedSmoother(process_noise="estimate", covariance=False).run(model, y, description="run")
    texts = [str(w.message) for w in shown if "trial warning" in str(w.message)]
    assert texts == [f"trial warning from {calls[1]} (run, at the process noise level tried when it stopped: "
                     f"{calls[1].removeprefix('run (').removesuffix(')')})"]
