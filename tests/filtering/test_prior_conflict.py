"""The prior-data conflict check of the material (diagnostics.prior_conflict): exact on linear-Gaussian
set-ups, standard normal and chi-square under the prior predictive, and a conflict found where it
was planted; through the iterated smoother on a small nonlinear model."""
import numpy as np
import pytest
from hypothesis import assume, given, settings, strategies as st

from sfem_filters.filtering import IteratedSmoother, LinearGaussianModel, diagnostics


def _problem(rng, p, m, uninformed=()):
    A = rng.standard_normal((p, p))
    P0 = A @ A.T / p + 0.3 * np.eye(p)
    G = rng.standard_normal((m, p))
    G[:, list(uninformed)] = 0.0
    B = rng.standard_normal((m, m))
    R = B @ B.T / m + 0.2 * np.eye(m)
    theta0 = rng.standard_normal(p)
    S = G @ P0 @ G.T + R
    K = P0 @ G.T @ np.linalg.inv(S)
    P_post = P0 - K @ G @ P0
    return theta0, P0, G, R, K, 0.5 * (P_post + P_post.T)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.integers(1, 6), st.integers(1, 8))
def test_z_is_the_shift_over_the_explained_sd(seed, p, m):
    rng = np.random.default_rng(seed)
    theta0, P0, G, R, K, P_post = _problem(rng, p, m)
    # the data's shares in the prior's metric: s^2 / (1 + s^2), s the singular values of
    # R^-1/2 G P0^1/2; a nearly singular G informs a direction too little to count (min_share)
    s = np.linalg.svd(np.linalg.solve(np.linalg.cholesky(R), G @ np.linalg.cholesky(P0)), compute_uv=False)
    assume(np.min(s[: min(p, m)] ** 2 / (1 + s[: min(p, m)] ** 2)) > 1e-4)
    theta = theta0 + rng.standard_normal(p)
    L = rng.standard_normal((3, p))
    out = diagnostics.prior_conflict(theta, P_post, theta0, P0, functionals=L)
    explained = np.array([l @ (K @ G @ P0) @ l for l in L])      # l P0 G^T S^-1 G P0 l^T
    share = explained / np.array([l @ P0 @ l for l in L])
    ok = share > 1e-6
    np.testing.assert_allclose(out["z"][ok], (L @ (theta - theta0))[ok] / np.sqrt(explained[ok]), rtol=1e-8)
    np.testing.assert_allclose(out["data_share"], share, rtol=1e-8, atol=1e-12)
    assert np.all((out["data_share"] >= -1e-12) & (out["data_share"] <= 1 + 1e-12))
    assert out["dof"] == min(p, m)
    # the flagged ones are exactly those beyond the threshold, by decreasing |z|
    beyond = [i for i in range(3) if ok[i] and abs(out["z"][i]) > out["threshold"]]
    assert sorted(out["flagged"]) == beyond
    assert [abs(out["z"][i]) for i in out["flagged"]] == sorted([abs(out["z"][i]) for i in beyond], reverse=True)


@pytest.mark.parametrize("seed", [0, 1])
def test_calibrated_under_the_prior_predictive(seed):
    rng = np.random.default_rng(seed)
    p, m, n = 5, 4, 4000
    theta0, P0, G, R, K, P_post = _problem(rng, p, m)
    truth = theta0 + rng.standard_normal((n, p)) @ np.linalg.cholesky(P0).T
    y = truth @ G.T + rng.standard_normal((n, m)) @ np.linalg.cholesky(R).T
    means = theta0 + (y - theta0 @ G.T) @ K.T
    runs = [diagnostics.prior_conflict(t, P_post, theta0, P0) for t in means]
    z = np.array([r["z"] for r in runs])
    q = np.array([r["chi2"] for r in runs])
    assert runs[0]["dof"] == m                        # 4 observations inform 4 directions of 5
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=0.06)
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.05)
    assert abs(q.mean() / m - 1.0) < 0.05
    assert np.mean([len(r["flagged"]) > 0 for r in runs]) < 0.02          # family-wise level 0.99


def test_uninformed_parameters_are_not_tested():
    rng = np.random.default_rng(3)
    theta0, P0, G, R, K, P_post = _problem(rng, 4, 6, uninformed=[2])
    P0[2, :] = P0[:, 2] = 0.0
    P0[2, 2] = 1.0
    P_post = P0 - P0 @ G.T @ np.linalg.solve(G @ P0 @ G.T + R, G @ P0)
    out = diagnostics.prior_conflict(theta0 + [0.1, 0.1, 5.0, 0.1], P_post, theta0, P0)
    assert np.isnan(out["z"][2]) and 2 not in out["flagged"] and out["dof"] == 3
    assert abs(out["data_share"][2]) < 1e-12


def test_a_planted_conflict_is_flagged_first():
    rng = np.random.default_rng(4)
    theta0, P0, G, R, K, P_post = _problem(rng, 4, 6)
    truth = theta0.copy()
    truth[1] += 12.0 * np.sqrt(P0[1, 1])            # 12 prior sd: a prior that excludes the truth
    y = G @ truth + np.linalg.cholesky(R) @ rng.standard_normal(6)
    mean = theta0 + K @ (y - G @ theta0)
    out = diagnostics.prior_conflict(mean, P_post, theta0, P0)
    assert out["log10_p"] < -6
    assert out["flagged"] and abs(out["z"][out["flagged"][0]]) > out["threshold"]


def test_saturating_parameter_held_by_the_prior_is_flagged():
    """y_t = a^t with a = sigmoid(theta), prior theta ~ N(0, 1): data from a = 0.999 (logit 6.9, far
    out on the sigmoid's flat tail) pull the smoother's mode to 6.6 prior sd, with a Laplace
    posterior through the nonlinearity; the check names the parameter. Data from a = 0.6 (logit 0.4,
    inside the prior) are not flagged."""

    def model_of():
        def transition(theta):
            a = 1.0 / (1.0 + np.exp(-theta[0]))
            return a * np.eye(1), (a * (1 - a) * np.ones((1, 1, 1)))
        return LinearGaussianModel(transition, H=np.eye(1), Q=1e-6 * np.eye(1), R=1e-4 * np.eye(1), x0=[1.0],
                                   P0=1e-6 * np.eye(1), n_frames=30, theta0=[0.0], prior_cov=np.eye(1))

    for a, conflict in ((0.999, True), (0.6, False)):
        model = model_of()
        y = (a ** np.arange(30))[:, None] + 1e-2 * np.random.default_rng(5).standard_normal((30, 1))
        fit = IteratedSmoother(max_iterations=40, covariance=False).run(model, y)
        out = diagnostics.prior_conflict(fit.theta, fit.P_theta, [0.0], np.eye(1))
        assert (out["flagged"] == [0]) is conflict, (a, fit.theta, out)


def test_bad_input_is_named():
    P = np.eye(2)
    with pytest.raises(ValueError, match="theta0"):
        diagnostics.prior_conflict([0.0, 1.0], P, [0.0], P)
    with pytest.raises(ValueError, match="P_post"):
        diagnostics.prior_conflict([0.0, 1.0], np.eye(3), [0.0, 0.0], P)
    with pytest.raises(ValueError, match="functionals"):
        diagnostics.prior_conflict([0.0, 1.0], 0.5 * P, [0.0, 0.0], P, functionals=np.ones((2, 3)))
    with pytest.raises(ValueError, match="level"):
        diagnostics.prior_conflict([0.0, 1.0], 0.5 * P, [0.0, 0.0], P, level=1.5)
    with pytest.raises(ValueError, match="^theta:"):
        diagnostics.prior_conflict([0.0, np.nan], 0.5 * P, [0.0, 0.0], P)
    with pytest.raises(ValueError, match="^theta: expected at least one"):
        diagnostics.prior_conflict([], np.zeros((0, 0)), [], np.zeros((0, 0)))
    with pytest.raises(ValueError, match="^P_prior: expected a symmetric positive definite"):
        diagnostics.prior_conflict([0.0, 1.0], 0.5 * P, [0.0, 0.0], np.diag([1.0, -1.0]))


def test_the_joint_test_does_not_depend_on_the_parameters_units():
    """Rescaling a parameter (a unit change) leaves z, the shares, the chi-square and its dof as they were,
    also when the scales differ by 8 orders of magnitude; a zero functional is not tested."""
    rng = np.random.default_rng(6)
    theta0, P0, G, R, K, P_post = _problem(rng, 2, 2)
    theta = theta0 + [0.5, -0.7]
    base = diagnostics.prior_conflict(theta, P_post, theta0, P0)
    S = np.diag([1e4, 1e-4])
    scaled = diagnostics.prior_conflict(S @ theta, S @ P_post @ S, S @ theta0, S @ P0 @ S)
    np.testing.assert_allclose(scaled["z"], base["z"], rtol=1e-8)
    np.testing.assert_allclose(scaled["data_share"], base["data_share"], rtol=1e-8)
    assert scaled["dof"] == base["dof"] == 2 and np.isclose(scaled["chi2"], base["chi2"], rtol=1e-8)
    out = diagnostics.prior_conflict(theta, P_post, theta0, P0, functionals=[[1.0, 0.0], [0.0, 0.0]])
    assert np.isfinite(out["z"][0]) and np.isnan(out["z"][1]) and out["data_share"][1] == 0.0
