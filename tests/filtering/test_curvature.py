"""The profile cost's exact Hessian (central differences of its exact gradient) and the exact Laplace."""
import warnings

import numpy as np
import pytest

from sfem_filters.benchmark.pinned import benchmark_model, pinned_benchmark
from sfem_filters.cardiac import annulus_sequence, build_model, prepare
from sfem_filters.fem import Parameterisation
from sfem_filters.filtering import (IteratedSmoother, ProfileHessian, gauss_newton_pass, optimal_trajectory,
                                    profile_hessian, profile_pass)
from sfem_filters.filtering.iterated import open_loop
from sfem_filters.filtering.protocol import parameter_prior
from sfem_filters.filtering.safeguards import Safeguards


@pytest.fixture(scope="module")
def misfit():
    """The smooth material basis on an annulus whose motion holds an undeclared active stress (the
    measured slice's misspecified baseline in small): the model, its data, the mode with the
    exact Laplace covariance, and a trajectory whose material is off the mode by about 1 sd."""
    seq = annulus_sequence("active_polar", n_frames=6, seed=0, amplitude=(0.3, -0.6))
    m, y = build_model(prepare(seq, 8), (), "penalty", "basis")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mode = IteratedSmoother(covariance=False, laplace="exact").run(m, y)
    z = mode.states.copy()
    sd = np.sqrt(np.diag(mode.P_theta_gauss_newton))
    z[:, m.n_restart:] += sd * np.random.default_rng(0).choice([-1.0, 1.0], len(sd))
    return m, y, z, mode


def _profile_cost(m, y, theta, like):
    theta0, P3 = parameter_prior(m)
    fit, found = profile_pass(m, y, theta, like, Safeguards())
    d = theta - theta0
    return fit + 0.5 * d @ np.linalg.solve(P3, d), found


def test_gradient_and_hessian_match_differences_of_the_cost(misfit):
    """Along random directions, the exact gradient and the Hessian (from gradients) agree with
    first and second central differences of the profile cost itself (values only)."""
    m, y, z, _ = misfit
    nr = m.n_restart
    theta = z[0, nr:]
    curv = profile_hessian(m, y, z)
    assert curv.evaluations == 2 * len(theta) + 1 and curv.asymmetry < 1e-2
    sd = np.sqrt(np.diag(np.linalg.inv(curv.gauss_newton)))
    rng = np.random.default_rng(3)
    c0, _ = _profile_cost(m, y, theta, z)
    for _ in range(3):
        v = rng.standard_normal(len(theta)) * sd
        cost = {eps: _profile_cost(m, y, theta + eps * v, z)[0] for eps in (-0.1, -0.01, 0.01, 0.1)}
        slope = (cost[0.01] - cost[-0.01]) / 0.02
        curvature = (cost[0.1] - 2 * c0 + cost[-0.1]) / 0.01
        assert abs(curv.gradient @ v - slope) <= 1e-3 * max(abs(slope), 1.0)
        assert abs(v @ curv.hessian @ v - curvature) <= 2e-2 * abs(curvature)


def test_gauss_newton_is_exact_where_every_residual_is_zero():
    """Data made by the model itself without noise, at the prior mean: every residual of the MAP
    cost is zero, so the term Gauss-Newton leaves out vanishes and the two Hessians agree."""
    bench = pinned_benchmark(0)
    m = benchmark_model(bench, "joint_ekf", parameterisation=Parameterisation.per_region(bench.middle))
    z = open_loop(m)
    y = np.array([np.asarray(m.hx(z[t]), float).ravel() for t in range(m.n_frames)])
    curv = profile_hessian(m, y, z)
    assert np.abs(curv.gradient).max() * np.sqrt(np.diag(np.linalg.inv(curv.gauss_newton))).max() < 1e-6
    np.testing.assert_allclose(curv.relative_eigenvalues(), 1.0, atol=1e-3)
    np.testing.assert_allclose(curv.sd_ratio(), 1.0, atol=1e-3)


def test_helpers_give_the_smoothers_own_profile_and_step(misfit):
    """From any trajectory, one profile pass at the mode's theta gives the smoother's MAP cost and
    trajectory, and the Gauss-Newton pass there the gradient the profile Hessian started from."""
    m, y, _, mode = misfit
    nr = m.n_restart
    start = open_loop(m)                                # any trajectory: the pass re-optimises it
    cost, found = _profile_cost(m, y, mode.theta, start)
    zz = optimal_trajectory(m, found)
    assert abs(cost - mode.cost) <= 1e-9 * abs(mode.cost)
    np.testing.assert_allclose(zz, mode.states, rtol=1e-6, atol=1e-9 * np.abs(mode.states).max())
    g, H, P = gauss_newton_pass(m, y, zz, Safeguards())
    np.testing.assert_allclose(H @ P, np.eye(len(g)), atol=1e-8)
    np.testing.assert_allclose(g, mode.curvature.gradient, rtol=1e-6, atol=1e-8)


def test_exact_laplace_reports_the_inverse_exact_hessian(misfit):
    """At a converged mode the exact Hessian is positive definite and its inverse is the reported
    covariance; the Gauss-Newton one is kept beside it, the inverse of the final pass's Hessian."""
    m, y, _, ex = misfit
    assert ex.converged and ex.laplace == "exact" and ex.curvature.positive_definite()
    np.testing.assert_allclose(ex.theta, ex.curvature.theta)
    np.testing.assert_allclose(ex.P_theta @ ex.curvature.hessian, np.eye(len(ex.theta)), atol=1e-8)
    np.testing.assert_allclose(ex.P_theta_gauss_newton @ ex.curvature.gauss_newton, np.eye(len(ex.theta)),
                               atol=1e-6)
    np.testing.assert_allclose(np.diag(ex.P_theta), ex.P_diag[0, m.n_restart:])
    gn = IteratedSmoother(covariance=False, max_iterations=1, damping=1e8)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        gn = gn.run(m, y)
    assert gn.laplace == "gauss-newton" and gn.curvature is None and gn.P_theta_gauss_newton is None


def test_bad_inputs_are_named(misfit):
    m, y, z, _ = misfit
    with pytest.raises(ValueError, match="laplace"):
        IteratedSmoother(laplace="newton")
    with pytest.raises(ValueError, match="states"):
        profile_hessian(m, y, z[:-1])
    with pytest.raises(ValueError, match="step_sd"):
        profile_hessian(m, y, z, step_sd=0.0)
    indefinite = ProfileHessian(theta=np.zeros(2), hessian=np.diag([1.0, -1.0]), gauss_newton=np.eye(2),
                                gradient=np.zeros(2), asymmetry=0.0, evaluations=5)
    assert not indefinite.positive_definite()
    np.testing.assert_allclose(indefinite.relative_eigenvalues(), [-1.0, 1.0])
    with pytest.raises(ValueError, match="not positive definite"):
        indefinite.covariance()
