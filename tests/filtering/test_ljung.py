"""Ljung's (1979) modification of the coupling term of the joint EKF (paper Eq. 40).

The demonstration system (Ljung's point: a parameter that couples noise into the state is
invisible to the plain EKF, whose coupling term ignores that the Kalman gain depends on it):

    x1_{t+1} = a x1_t + b x2_t,   x2_{t+1} = w_t ~ N(0, 1),   y_t = x1_t + v_t ~ N(0, r)

with theta = (a, log b). The mean map's derivative in log b is b x2_{t|t}, and x2_{t|t} = 0
always (x2_t is white and not yet seen), so the plain EKF never moves log b from its prior and,
with the wrong gain, biases a as well. The modified EKF is a recursive prediction-error method
and converges to the truth.
"""
import warnings

import numpy as np
import pytest
from helpers import simulate, small_model

from sfem_filters.fem.material import Parameterisation
from sfem_filters.fem.mesh import rectangle_mesh
from sfem_filters.filtering import (
    ENGINES,
    LJUNG_MAX_PARAMS,
    LinearGaussianModel,
    LjungCoupling,
    cyclic_estimate,
    filter_loop,
)

A_TRUE, B_TRUE, R_NOISE = 0.8, 1.0, 0.3
START = (0.5, np.log(0.3))


def _transition(theta):
    a, log_b = theta
    b = np.exp(log_b)
    A = np.array([[a, b], [0.0, 0.0]])
    dA = np.zeros((2, 2, 2))
    dA[0, 0, 0] = 1.0
    dA[1, 0, 1] = b
    return A, dA


def _data(seed, n):
    rng = np.random.default_rng(seed)
    A = np.array([[A_TRUE, B_TRUE], [0.0, 0.0]])
    x = np.zeros(2)
    y = np.empty((n, 1))
    for t in range(n):
        y[t, 0] = x[0] + rng.normal() * np.sqrt(R_NOISE)
        x = A @ x + np.array([0.0, rng.normal()])
    return y


def _model(n, start=START, prior=1.0):
    return LinearGaussianModel(_transition, [[1.0, 0.0]], np.diag([0.0, 1.0]), [[R_NOISE]], np.zeros(2),
                               np.eye(2), n, theta0=start, prior_cov=prior * np.eye(2))


def _estimate(seed, n, ljung, engine="structured"):
    model = _model(n)
    eng = ENGINES[engine](model, ljung=ljung)
    eng.reset(model.x0, model.P0)
    states = filter_loop(eng, model, _data(seed, n))
    return states[-1, 2], np.exp(states[-1, 3])


def test_plain_ekf_is_biased_and_ljung_converges():
    """2000 samples, 4 seeds (``pytest -s -k biased`` prints the means): plain a = 0.883 with b
    stuck at its prior 0.3; modified a = 0.774, b = 1.065 (truth 0.8, 1.0). With 8000 samples
    (2 seeds) the modified one reaches a = 0.792, b = 1.028, the plain one stays at a = 0.889."""
    plain = np.array([_estimate(s, 2000, ljung=False) for s in range(4)])
    mod = np.array([_estimate(s, 2000, ljung=True) for s in range(4)])
    plain_a, plain_b = plain.mean(axis=0)
    mod_a, mod_b = mod.mean(axis=0)
    print(f"\nplain EKF: a = {plain_a:.4f}, b = {plain_b:.4f}; Ljung: a = {mod_a:.4f}, b = {mod_b:.4f} "
          f"(truth a = {A_TRUE}, b = {B_TRUE})")
    # the plain EKF: log b never moves, a is measurably biased on every seed
    np.testing.assert_allclose(plain[:, 1], np.exp(START[1]), rtol=1e-12)
    assert abs(plain_a - A_TRUE) > 0.06
    assert np.all(np.abs(plain[:, 0] - A_TRUE) > 0.05)
    # Ljung's modification: both parameters near the truth
    assert abs(mod_a - A_TRUE) < 0.04
    assert abs(mod_b - B_TRUE) < 0.15
    assert abs(mod_a - A_TRUE) < 0.5 * abs(plain_a - A_TRUE)


def test_all_engines_run_the_same_modified_filter():
    names = [n for n, cls in ENGINES.items() if cls.supports_ljung]
    assert {"filterpy", "structured", "ud"} <= set(names)
    a = {name: _estimate(3, 60, ljung=True, engine=name) for name in names}
    for name in names:
        np.testing.assert_allclose(a[name], a["structured"], rtol=1e-9)
    assert abs(a["structured"][1] - np.exp(START[1])) > 1e-3      # log b moved (plain: it cannot)


def _gain_derivative_check(model, y, steps, h=1e-6):
    """Run the gain sensitivity recursion at fixed theta (zero prior covariance, so theta stays
    put) and compare dK_t/dtheta_i with central differences of K_t(theta +- h e_i)."""
    def run(theta):
        m = model(theta)
        eng = ENGINES["structured"](m, ljung=True)
        eng.reset(m.x0, m.P0)
        gains, dgains = [], []
        for t in range(steps):
            if t > 0:
                eng.predict(t - 1)
            eng.update(y[t], t, np.ones(m.dim_obs, bool))
            gains.append(eng.ljung.gain.copy())
            dgains.append(eng.ljung.gain_derivative.copy())
        return gains, dgains

    theta0 = model(None).x0[model(None).n_restart:]
    _, dK = run(theta0)
    worst = 0.0
    for i in range(len(theta0)):
        e = np.zeros(len(theta0))
        e[i] = h
        Kp, _ = run(theta0 + e)
        Km, _ = run(theta0 - e)
        for t in range(1, steps):
            fd = (Kp[t] - Km[t]) / (2 * h)
            worst = max(worst, np.abs(fd - dK[t][i]).max() / max(np.abs(dK[t][i]).max(), 1e-300))
    return worst


def test_gain_sensitivity_recursion_matches_finite_differences():
    y = _data(1, 8)
    worst = _gain_derivative_check(lambda th: _model(8, START if th is None else th, prior=0.0), y, 8)
    assert worst < 1e-6


def _fem_region_model(theta=None, rng_seed=5):
    rng = np.random.default_rng(rng_seed)
    mesh = rectangle_mesh(0.02, 0.02, 3, 3)
    labels = (mesh.centroids[:, 0] > 0.01).astype(int)
    m = small_model(rng, mesh=mesh, parameterisation=Parameterisation.per_region(labels), n_frames=5)
    if theta is not None:
        m.x0 = m.x0.copy()
        m.x0[m.n_restart:] = theta
    m.P0 = m.P0.copy()
    m.P0[m.n_restart:, m.n_restart:] = 0.0
    return m


def test_fem_transition_derivatives_and_gain_sensitivities():
    """On a tiny mesh with a two-region material (4 parameters): dA/dtheta of the model equals
    finite differences of its A, and the Ljung gain derivatives those of the gain."""
    m = _fem_region_model()
    z = m.x0.copy()
    nr = m.n_restart
    dA = m.transition_derivatives(z, 0)
    assert dA.shape == (4, nr, nr)
    for i in range(4):
        zp, zm = z.copy(), z.copy()
        zp[nr + i] += 1e-5
        zm[nr + i] -= 1e-5
        fd = (m.F_jacobian(zp, 0)[:nr, :nr] - m.F_jacobian(zm, 0)[:nr, :nr]) / 2e-5
        assert np.abs(fd - dA[i]).max() <= 1e-6 * np.abs(dA[i]).max()
    y = simulate(m, np.random.default_rng(0), 1e-5)
    assert _gain_derivative_check(lambda th: _fem_region_model(th), y, 4, h=1e-5) < 1e-5


def test_cyclic_estimate_with_ljung_on_a_region_model():
    """The option runs through cyclic_estimate on the FEM model, changes the result and keeps the
    material admissible; the checkpoint of a plain run is not taken for a modified one."""
    rng = np.random.default_rng(5)
    mesh = rectangle_mesh(0.02, 0.02, 3, 3)
    labels = (mesh.centroids[:, 0] > 0.01).astype(int)
    m = small_model(rng, mesh=mesh, parameterisation=Parameterisation.per_region(labels), n_frames=5)
    y = simulate(m, rng, 1e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        plain = cyclic_estimate(m, y, max_loops=2, tol=1e-12)
        mod = cyclic_estimate(m, y, max_loops=2, tol=1e-12, ljung=True)
        mod_ud = cyclic_estimate(m, y, max_loops=2, tol=1e-12, ljung=True, engine="ud")
    assert np.all(np.isfinite(mod.theta)) and not np.array_equal(mod.theta, plain.theta)
    np.testing.assert_allclose(mod_ud.theta, mod.theta, rtol=1e-9)
    mat = m.material_of_theta(mod.theta)
    assert np.all(mat.E > 0) and np.all((mat.nu > 0) & (mat.nu < 0.5))


def test_ljung_argument_errors():
    rng = np.random.default_rng(0)
    mesh = rectangle_mesh(0.03, 0.03, 4, 4)
    per_element = small_model(rng, mesh=mesh, n_frames=3)
    assert per_element.dim_theta > LJUNG_MAX_PARAMS
    with pytest.raises(ValueError, match=rf"ljung: expected at most {LJUNG_MAX_PARAMS} estimated parameters.*"
                                         r"got 36; use a per-region"):
        LjungCoupling(per_element)
    fixed = small_model(rng, mesh=mesh, parameterisation=None, n_frames=3)
    with pytest.raises(ValueError, match="ljung: expected a model that estimates parameters"):
        cyclic_estimate(fixed, np.zeros((3, fixed.dim_obs)), ljung=True)
    with pytest.raises(TypeError, match="ljung: expected True or False, got 'yes'"):
        cyclic_estimate(fixed, np.zeros((3, fixed.dim_obs)), ljung="yes")
