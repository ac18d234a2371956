"""A process noise per frame interval (ProcessNoiseProfile): it reaches the smoother, against a hand-built filter.

The reference is a time-varying Kalman filter and RTS smoother written out here in plain numpy
(``x_t+1 = A x_t + w_t``, ``w_t ~ N(0, s_t Q)``), not the library's code.
"""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.filtering import (
    IteratedSmoother,
    LinearGaussianModel,
    MapObjective,
    ProcessNoiseProfile,
    cyclic_estimate,
    linearise,
    process_profile,
    smooth,
)
from sfem_filters.filtering.protocol import model_fingerprint
from sfem_filters.filtering.smoother import kalman_forward, rts_reference


class ProfiledModel(LinearGaussianModel):
    """The template model with a factor on Q per frame interval."""

    def __init__(self, *args, profile=None, **kwargs):
        super().__init__(*args, **kwargs)
        self._profile = profile

    def process_profile(self):
        return self._profile


def _system(T=12, seed=0):
    rng = np.random.default_rng(seed)
    A = np.array([[1.0, 1.0], [0.0, 0.9]])            # a damped constant-velocity pair
    H = np.array([[1.0, 0.0]])
    Q = np.diag([0.01, 0.04])
    R = np.array([[0.2]])
    x0, P0 = np.array([0.0, 0.5]), np.diag([0.3, 0.2])
    y = rng.standard_normal((T, 1)) + np.arange(T)[:, None] * 0.3
    y[4] = np.nan                                      # a frame with nothing observed
    return A, H, Q, R, x0, P0, y


def _hand_built(A, H, Q, R, x0, P0, y, s):
    """Time-varying Kalman filter and RTS smoother; returns smoothed means, covariances, log-likelihood."""
    T, n = len(y), len(x0)
    x, P = x0.copy(), P0.copy()
    xf, Pf, xp, Pp, ll = [], [], [None], [None], 0.0
    for t in range(T):
        if t > 0:
            x, P = A @ x, A @ P @ A.T + s[t - 1] * Q
            xp.append(x)
            Pp.append(P)
        if np.isfinite(y[t]).all():
            S = H @ P @ H.T + R
            e = y[t] - H @ x
            ll -= 0.5 * (float(e @ np.linalg.solve(S, e)) + np.log(np.linalg.det(S)) + len(e) * np.log(2 * np.pi))
            K = P @ H.T @ np.linalg.inv(S)
            x, P = x + K @ e, (np.eye(n) - K @ H) @ P
        xf.append(x)
        Pf.append(P)
    xs, Ps = [None] * T, [None] * T
    xs[-1], Ps[-1] = xf[-1], Pf[-1]
    for t in range(T - 2, -1, -1):
        G = Pf[t] @ A.T @ np.linalg.inv(Pp[t + 1])
        xs[t] = xf[t] + G @ (xs[t + 1] - xp[t + 1])
        Ps[t] = Pf[t] + G @ (Ps[t + 1] - Pp[t + 1]) @ G.T
    return np.array(xs), np.array(Ps), ll


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(0.05, 20.0), min_size=11, max_size=11))
def test_a_per_interval_process_noise_reaches_the_filter_and_the_smoother(s):
    A, H, Q, R, x0, P0, y = _system()
    s = np.array(s)
    model = ProfiledModel(A, H, Q, R, x0, P0, len(y), profile=s)
    assert isinstance(model, ProcessNoiseProfile)
    lin = linearise(model, np.tile(model.x0, (len(y), 1)))
    xs, Ps, ll = _hand_built(A, H, Q, R, x0, P0, y, s)
    fw = kalman_forward(lin, y)
    assert np.isclose(fw.log_likelihood, ll, rtol=1e-9, atol=1e-9)
    sm = smooth(lin, y, covariance=True, outputs={"x": np.eye(2)})
    assert np.allclose(sm.smoothed[:, :2], xs, rtol=1e-8, atol=1e-9)
    assert np.allclose(sm.variances["x"], np.diagonal(Ps, axis1=1, axis2=2), rtol=1e-8, atol=1e-10)
    means = smooth(lin, y, covariance=False)                       # the disturbance smoother's path
    assert np.allclose(means.smoothed[:, :2], xs, rtol=1e-8, atol=1e-9)
    ref, Pref = rts_reference(lin, y)
    assert np.allclose(ref[:, :2], xs, rtol=1e-8, atol=1e-9) and np.allclose(Pref[:, :2, :2], Ps, atol=1e-10)
    # the iterated smoother (material fixed: one pass) gives the same trajectory
    assert np.allclose(IteratedSmoother().run(model, y).states[:, :2], xs, rtol=1e-8, atol=1e-9)


def test_a_profile_of_ones_changes_nothing_and_a_burst_lets_the_smoother_follow_it():
    A, H, Q, R, x0, P0, y = _system()
    T = len(y)
    plain = LinearGaussianModel(A, H, Q, R, x0, P0, T)
    ones = ProfiledModel(A, H, Q, R, x0, P0, T, profile=np.ones(T - 1))
    z = np.tile(plain.x0, (T, 1))
    a, b = smooth(linearise(plain, z), y), smooth(linearise(ones, z), y)
    assert np.array_equal(a.smoothed, b.smoothed)
    assert linearise(plain, z).q_scale is None
    burst = np.ones(T - 1)
    burst[6] = 50.0
    c = smooth(linearise(ProfiledModel(A, H, Q, R, x0, P0, T, profile=burst), z), y)
    assert not np.allclose(c.smoothed, a.smoothed)
    # the fingerprint of a model with a profile differs from the one without
    assert model_fingerprint(ProfiledModel(A, H, Q, R, x0, P0, T, profile=burst)) != model_fingerprint(plain)


def test_the_map_cost_weighs_each_interval_by_its_own_process_noise():
    A, H, Q, R, x0, P0, y = _system()
    T = len(y)
    s = np.linspace(0.5, 4.0, T - 1)
    model = ProfiledModel(A, H, Q, R, x0, P0, T, profile=s)
    z = np.random.default_rng(3).standard_normal((T, 2))
    w = z[1:] - z[:-1] @ A.T
    expected = 0.5 * sum(float(w[t] @ np.linalg.solve(s[t] * Q, w[t])) for t in range(T - 1))
    assert np.isclose(MapObjective(model, y).parts(z)["process"], expected, rtol=1e-12)


def test_bad_profiles_and_the_cyclic_engines_are_refused_naming_what_is_wrong():
    A, H, Q, R, x0, P0, y = _system()
    T = len(y)
    for bad in (np.ones(T), np.r_[np.ones(T - 2), 0.0], np.r_[np.ones(T - 2), np.nan]):
        with pytest.raises(ValueError, match="process_profile"):
            process_profile(ProfiledModel(A, H, Q, R, x0, P0, T, profile=bad))
    with pytest.raises(ValueError, match="model: a process noise profile"):
        cyclic_estimate(ProfiledModel(A, H, Q, R, x0, P0, T, profile=np.ones(T - 1)), y, max_loops=1)
    assert process_profile(LinearGaussianModel(A, H, Q, R, x0, P0, T)) is None
