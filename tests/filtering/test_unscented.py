"""filterpy's UKF and Moireau & Chapelle's reduced-order UKF on the library's models: exact where
the model is linear, the simplex's moments, and the joint problem through the cyclic driver."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.benchmark import benchmark_model, pinned_benchmark
from sfem_filters.filtering import CyclicEKF, filter_loop, make_engine, simplex_points
from sfem_filters.filtering.ekf import FilterpyEngine
from sfem_filters.filtering.linear import LinearObservation
from sfem_filters.filtering.roukf import ROUKFEngine


@given(p=st.integers(1, 40))
def test_simplex_points_have_zero_mean_and_identity_second_moment(p):
    I = simplex_points(p)
    assert I.shape == (p, p + 1)
    np.testing.assert_allclose(I.sum(axis=1), 0, atol=1e-10)
    np.testing.assert_allclose(I @ I.T / (p + 1), np.eye(p), atol=1e-10)


class AdditiveParameterModel(LinearObservation):
    """x_{t+1} = A x_t + B theta, y = H x: linear in z = [x; theta], parameters as constant loads."""

    def __init__(self, rng, n=4, p=2, m=3, n_frames=12):
        self.n_restart, self.dim_state, self.dim_obs, self.n_frames = n, n + p, m, n_frames
        self.estimates_material = True
        Q, _ = np.linalg.qr(rng.normal(size=(n, n)))
        self.A = 0.95 * Q
        self.B = rng.normal(size=(n, p))
        self._H = np.hstack([rng.normal(size=(m, n)), np.zeros((m, p))])
        self.x0 = np.concatenate([np.zeros(n), rng.normal(size=p)])
        G = rng.normal(size=(p, p))
        self.P0 = np.zeros((n + p, n + p))
        self.P0[n:, n:] = G @ G.T + 0.5 * np.eye(p)
        self.Q = np.zeros((n + p, n + p))
        self.R = 0.1 * np.eye(m)
        self.F = np.block([[self.A, self.B], [np.zeros((p, n)), np.eye(p)]])

    def fx(self, z, t):
        return (self.F @ np.asarray(z, float).ravel()).reshape(np.shape(z))

    def F_jacobian(self, z, t):
        return self.F


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000))
def test_reduced_order_ukf_is_the_kalman_filter_of_a_rank_p_linear_problem(seed):
    rng = np.random.default_rng(seed)
    model = AdditiveParameterModel(rng)
    y = rng.normal(size=(model.n_frames, model.dim_obs))
    y[3, 1] = np.nan                                  # a missing datum
    ref, rou = FilterpyEngine(model), ROUKFEngine(model)
    for e in (ref, rou):
        e.reset(model.x0, model.P0)
    a = filter_loop(ref, model, y)
    b = filter_loop(rou, model, y)
    np.testing.assert_allclose(b, a, rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(rou.P, ref.P, rtol=1e-7, atol=1e-10)


def test_ukf_agrees_with_the_ekf_where_the_model_is_linear():
    bench = pinned_benchmark(0)
    model = benchmark_model(bench, "perfect_kf")          # material fixed: linear in the state
    ekf, ukf = make_engine("filterpy", model), make_engine("ukf", model)
    for e in (ekf, ukf):
        e.reset(model.x0, model.P0)
    a = filter_loop(ekf, model, bench.observations)
    b = filter_loop(ukf, model, bench.observations)
    scale = np.abs(a).max()
    np.testing.assert_allclose(b, a, atol=1e-8 * scale)
    np.testing.assert_allclose(ukf.P, ekf.P, atol=1e-8 * np.abs(ekf.P).max())
    # and filterpy's own loop on model.make_ukf(), as its docstring drives it
    u = model.make_ukf()
    out = []
    for t, yt in enumerate(bench.observations):
        if t > 0:
            u.predict(t=t - 1)
        u.update(yt, t=t)
        out.append(u.x.copy())
    np.testing.assert_allclose(np.array(out), a, atol=1e-8 * scale)


def test_reduced_order_ukf_runs_the_joint_problem_in_the_cyclic_driver(tmp_path):
    bench = pinned_benchmark(0)
    model = benchmark_model(bench, "joint_ekf")
    ckpt = str(tmp_path / "c.npz")
    res = CyclicEKF(max_loops=2, engine="roukf").run(model, bench.observations, checkpoint=ckpt)
    nx = model.n_restart
    prior = model.P0[nx:, nx:]
    assert np.all(np.isfinite(res.theta)) and res.loops == 2
    # the data carry information: the posterior is inside the prior (Loewner order) and definite
    assert np.linalg.eigvalsh(prior - res.P_theta).min() > -1e-10 * np.abs(prior).max()
    assert np.linalg.eigvalsh(res.P_theta).min() > 0
    assert np.trace(res.P_theta) < 0.9 * np.trace(prior)
    # a finished checkpoint gives the same run back
    again = CyclicEKF(max_loops=2, engine="roukf").run(model, bench.observations, checkpoint=ckpt)
    np.testing.assert_array_equal(again.theta, res.theta)
    with pytest.raises(ValueError, match="ljung"):
        ROUKFEngine(model, ljung=True)
    with pytest.raises(ValueError, match="parameters"):
        ROUKFEngine(benchmark_model(bench, "perfect_kf"))
