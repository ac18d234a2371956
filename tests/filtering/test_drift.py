"""The cyclic carry-over of section 2.7 on a model where the EKF is exact, and the drift
diagnostic that measures each loop's step against the carried uncertainty."""
import numpy as np
import pytest
from helpers import bias_model as _model
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.filtering import History, LinearGaussianModel, cyclic_estimate
from sfem_filters.filtering.diagnostics import material_drift


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 4), p=st.integers(1, 3), loops=st.integers(2, 6))
def test_carried_loops_add_one_cycle_of_information_each(seed, n, p, loops):
    """Linear case: loop k's posterior is the prior plus k copies of one cycle's information,
    ``P_k^-1 = P3^-1 + k J``, ``P_k^-1 theta_k = P3^-1 theta_0 + k b``, so each loop's step
    shrinks like 1/k; material_drift reports exactly these steps over the carried sd."""
    rng = np.random.default_rng(seed)
    model, y = _model(rng, n, p, min(n, 2), 10)
    nr = model.n_restart
    th0, P3 = model.x0[nr:], model.P0[nr:, nr:]
    with pytest.warns(RuntimeWarning, match="did not converge"):
        one = cyclic_estimate(model, y, max_loops=1, tol=1e-300)
    I0 = np.linalg.inv(P3)
    I1 = np.linalg.inv(one.P_theta)
    J, b = I1 - I0, I1 @ one.theta - I0 @ th0
    with pytest.warns(RuntimeWarning, match="did not converge"):
        res = cyclic_estimate(model, y, max_loops=loops, tol=1e-300)
    drift = material_drift(model, res.history)
    np.testing.assert_array_equal(drift["loops"], np.arange(loops))
    prev = th0
    for k in range(1, loops + 1):
        Pk = np.linalg.inv(I0 + k * J)
        thk = Pk @ (I0 @ th0 + k * b)
        last = res.history.loop_rows(k - 1)[-1]
        scale = max(np.abs(thk).max(), 1.0)
        np.testing.assert_allclose(res.history.x[last][nr:], thk, rtol=0, atol=1e-8 * scale)
        np.testing.assert_allclose(res.history.P_diag[last][nr:], np.diag(Pk), rtol=1e-7)
        d = (thk - prev) / np.sqrt(np.diag(Pk))
        assert drift["max_sd"][k - 1] == pytest.approx(np.abs(d).max(), rel=1e-6, abs=1e-9)
        assert drift["rms_sd"][k - 1] == pytest.approx(np.sqrt(np.mean(d ** 2)), rel=1e-6, abs=1e-9)
        prev = thk
    np.testing.assert_allclose(res.P_theta, Pk, rtol=1e-7, atol=1e-12 * np.abs(Pk).max())


def test_material_drift_errors_name_their_argument():
    rng = np.random.default_rng(0)
    model, y = _model(rng, 2, 1, 2, 5)
    with pytest.raises(TypeError, match="history"):
        material_drift(model, [1, 2])
    with pytest.raises(ValueError, match="history: expected a run"):
        material_drift(model, History())
    fixed = LinearGaussianModel(np.eye(2) * 0.5, np.eye(2), np.eye(2), np.eye(2), np.zeros(2), np.eye(2), 4)
    res = cyclic_estimate(fixed, rng.standard_normal((4, 2)))
    with pytest.raises(ValueError, match="model: expected a model that estimates"):
        material_drift(fixed, res.history)
