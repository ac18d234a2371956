"""Each segment's excess error partially pooled with the six segments' (strain_bands.pooling_weights,
moment_mean_variance; strain_route.curve_discrepancy)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import gaussian_filter1d

from sfem_filters.cardiac.strain_bands import (curve_curvature, curve_noise_variance, discrepancy_variance,
                                               moment_mean_variance, pooling_weights)
from sfem_filters.cardiac.strain_route import curve_discrepancy


def _ar1(rng, n, rho, size):
    x = np.empty((size, n))
    x[:, 0] = rng.standard_normal(size) / np.sqrt(1 - rho ** 2)
    for t in range(1, n):
        x[:, t] = rho * x[:, t - 1] + rng.standard_normal(size)
    return x


@pytest.mark.parametrize("rho", [0.0, 0.5, 0.8])
def test_the_mean_moments_sampling_variance_allows_for_serial_correlation(rho):
    """Against the spread of the means of 4000 AR(1) series: within 25% (var / n alone is 9 times too
    small at rho 0.8)."""
    rng = np.random.default_rng(3)
    x = _ar1(rng, 200, rho, 4000)
    empirical = np.var(x.mean(axis=1))
    estimated = np.mean([moment_mean_variance(s) for s in x[:400]])
    assert estimated == pytest.approx(empirical, rel=0.25)


def test_the_mean_moments_sampling_variance_errors_name_the_argument():
    with pytest.raises(ValueError, match="moments: expected at least 2 finite"):
        moment_mean_variance([1.0, np.nan])
    assert moment_mean_variance([2.0, 2.0, 2.0]) == 0.0


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3), min_size=2, max_size=8), st.floats(0.0, 1e3), st.floats(0.0, 1e6))
def test_pooling_weights_lie_in_0_1_and_vanish_when_the_groups_differ_by_no_more_than_their_noise(own, base, v):
    own = np.asarray(own)
    w = pooling_weights(own, np.full(own.size, base), np.full(own.size, v))
    assert np.all((w >= 0) & (w <= 1))
    assert np.all(pooling_weights(own, own, np.full(own.size, v)) == 0)        # no deviation: all pooled
    if v >= np.var(own):                                                       # deviations within the noise
        assert np.all(w == 0)


def test_pooling_weights_keep_a_group_that_differs_by_far_more_than_its_noise():
    w = pooling_weights([1.0, 1.0, 1.0, 1.0, 1.0, 10.0], np.full(6, 2.5), np.full(6, 0.01))
    assert np.all(w > 0.99)
    with pytest.raises(ValueError, match="sampling_var: expected non-negative"):
        pooling_weights([1.0, 2.0], [1.0, 1.0], [-1.0, 0.0])


def _segments(rng, F=60, offset=0.0):
    m = np.tile(0.2 * np.sin(np.linspace(0, np.pi, F))[:, None], (1, 7))
    d = 0.002 * rng.standard_normal((F, 7))
    d[:, 1:] += 0.1 * m[:, 1:] * np.cos(np.linspace(0, 3, F))[:, None]       # each segment's excess, ~10% of m
    d[:, 6] += offset                                                           # one segment's tracks biased
    return d, m


def test_segments_that_differ_only_by_noise_share_the_pooled_model():
    d, m = _segments(np.random.default_rng(5))
    tau, det = curve_discrepancy(d, m, details=True, curvature=False)
    assert np.all(det["weights"] < 0.2)
    assert np.allclose(tau[1:], tau[1], rtol=0.2, atol=1e-7)


def test_a_segment_whose_tracks_carry_a_bias_of_their_own_keeps_it_and_does_not_widen_the_others():
    """One segment's reference offset by 3 points: pooled, every segment's excess took a sixth of it;
    partially pooled, that segment keeps most of it and the other five stay near their own."""
    d, m = _segments(np.random.default_rng(5), offset=0.03)
    tau, det = curve_discrepancy(d, m, details=True, curvature=False)
    excess = tau[1:, 0] + tau[1:, 1] * np.mean(m[:, 1:] ** 2, axis=0)
    pooled = det["pooled"][0] + det["pooled"][1] * np.mean(m[:, 1] ** 2)
    clean, _ = curve_discrepancy(*_segments(np.random.default_rng(5)), details=True, curvature=False)
    clean_excess = clean[1, 0] + clean[1, 1] * np.mean(m[:, 1] ** 2)
    assert np.all(det["weights"][:5] > 0.9)          # far from the pooled fit, each by far more than its noise
    assert det["weights"][5] > 0.5                   # a smooth bias: few independent frames, so partly pooled
    assert excess[5] > 0.6 * 0.03 ** 2
    assert np.all(excess[:5] < 0.3 * pooled)
    assert np.all(excess[:5] < 1.5 * clean_excess)


def test_segments_smoothed_at_the_onset_share_a_bend_term():
    """Six segments whose estimates lead a kinked onset the same way (a Gaussian smoothing of 4 frames),
    each seen through its own noise: they differ only by noise, so they share the pooled model, whose
    bend term is positive and whose variance matches the bias's mean square."""
    rng = np.random.default_rng(3)
    F = 60
    t = np.arange(F, dtype=float)
    truth = 0.4 * np.clip((t - 15) / 20, 0, 1) ** 2 * np.exp(-np.clip(t - 35, 0, None) / 10)
    m1 = gaussian_filter1d(truth, 4.0, mode="nearest")
    m = np.tile(m1[:, None], (1, 7))
    d = (truth - m1)[:, None] + 0.001 * rng.standard_normal((F, 7))
    tau, det = curve_discrepancy(d, m, details=True)
    assert tau.shape == (7, 3) and det["pooled"].shape == (3,)
    assert np.all(det["weights"] < 0.2) and det["pooled"][2] > 0
    var = det["pooled"][0] + det["pooled"][1] * m1 ** 2 + det["pooled"][2] * curve_curvature(m1) ** 2
    assert np.mean(var) == pytest.approx(np.mean((truth - m1) ** 2), rel=0.5)


def test_the_pooled_fit_takes_each_segments_own_bend_not_the_joins_between_them():
    """Segments whose curves start and end at different values: the pooled fit is the moment fit of their
    frames concatenated with each curve's own second difference, not one taken across the joins."""
    rng = np.random.default_rng(11)
    F = 50
    t = np.linspace(0, 1, F)
    m = np.column_stack([0.05 * g + 0.2 * t ** 2 for g in range(7)])               # each a different ramp
    d = 0.002 * rng.standard_normal((F, 7)) + 0.05 * curve_curvature(m) * 40 + 0.02 * m
    tau, det = curve_discrepancy(d, m, details=True)
    segs = range(1, 7)
    noise = np.concatenate([np.full(F, curve_noise_variance(d[:, g])) for g in segs])
    own_bends = np.concatenate([curve_curvature(m[:, g]) for g in segs])
    want = discrepancy_variance(np.concatenate([d[:, g] for g in segs]), np.concatenate([m[:, g] for g in segs]),
                                noise, own_bends)
    assert np.allclose(det["pooled"], want)
    across = discrepancy_variance(np.concatenate([d[:, g] for g in segs]), np.concatenate([m[:, g] for g in segs]),
                                  noise, True)
    assert not np.allclose(det["pooled"], across)

