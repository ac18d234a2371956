"""The U-D factorised (Bierman-Thornton) engine: same filter as the Joseph form, P = U D U^T
with D >= 0 by construction, and the case where the covariance form loses definiteness."""
import warnings

import mpmath as mp
import numpy as np
import pytest
from helpers import count_calls, random_block_mesh, simulate, small_model
from hypothesis import given, settings
from hypothesis import strategies as st

import sfem_filters.filtering.cyclic as cyclic_module
from sfem_filters.filtering import (
    ENGINES,
    LinearGaussianModel,
    Safeguards,
    UDEngine,
    bierman_update,
    cyclic_estimate,
    filter_loop,
    load_checkpoint,
    mwgs,
    psd_factor,
    ud_factor,
)


def _relmax(a, b):
    return np.abs(a - b).max() / np.abs(b).max()


@settings(max_examples=12, deadline=None)
@given(n=st.integers(1, 7), seed=st.integers(0, 10_000), rank=st.integers(0, 7))
def test_ud_factor_and_mwgs_reproduce_the_matrix(n, seed, rank):
    """U unit upper triangular, d >= 0, U diag(d) U^T = P, also for singular P (rank < n)."""
    rng = np.random.default_rng(seed)
    B = rng.standard_normal((n, min(rank, n)))
    P = B @ B.T
    U, d = ud_factor(P)
    assert np.all(d >= 0)
    np.testing.assert_array_equal(np.tril(U, -1), 0.0)
    np.testing.assert_array_equal(np.diag(U), 1.0)
    assert np.abs((U * d) @ U.T - P).max() <= 1e-12 * max(np.abs(P).max(), 1.0)
    W = rng.standard_normal((n, n + 3))
    dw = np.abs(rng.standard_normal(n + 3))
    dw[rng.integers(0, n + 3)] = 0.0                        # a zero weight (singular Q block)
    U2, d2 = mwgs(W, dw)
    assert np.all(d2 >= 0)
    np.testing.assert_array_equal(np.tril(U2, -1), 0.0)
    np.testing.assert_allclose((U2 * d2) @ U2.T, (W * dw) @ W.T, rtol=0, atol=1e-11 * np.abs(W).max() ** 2 * 10)


def test_bierman_update_equals_the_kalman_update():
    rng = np.random.default_rng(4)
    B = rng.standard_normal((5, 5))
    P = B @ B.T
    h = rng.standard_normal(5)
    U, d = ud_factor(P)
    gain, s = bierman_update(U, d, h, 0.3)
    s_ref = h @ P @ h + 0.3
    np.testing.assert_allclose(s, s_ref, rtol=1e-13)
    np.testing.assert_allclose(gain, P @ h / s_ref, rtol=1e-12)
    np.testing.assert_allclose((U * d) @ U.T, P - np.outer(P @ h, P @ h) / s_ref, rtol=0, atol=1e-12 * np.abs(P).max())
    assert np.all(d >= 0)


def test_indefinite_input_is_an_error_naming_P():
    P = np.diag([1.0, -1.0, 2.0])
    with pytest.raises(ValueError, match="P: expected a positive semi-definite covariance"):
        ud_factor(P)
    with pytest.raises(ValueError, match=r"Q: expected a positive semi-definite matrix"):
        psd_factor(np.array([[1.0, 2.0], [2.0, 1.0]]))


def test_singular_Q_is_factored_without_its_zero_part():
    """The model's Q has zero blocks (theta): the factor keeps only the non-zero variances."""
    Q = np.diag([1e-12, 0.0, 4e-8, 0.0])
    G, q = psd_factor(Q)
    assert G.shape == (4, 2) and np.all(q > 0)
    np.testing.assert_array_equal((G * q) @ G.T, Q)
    Qd = np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 0.0]])
    G, q = psd_factor(Qd)
    assert G.shape == (3, 2)
    np.testing.assert_allclose((G * q) @ G.T, Qd, atol=1e-15)


@pytest.mark.parametrize("seed", [0, 7])
def test_ud_matches_the_joseph_engines_with_missing_rows(seed):
    """Joint EKF on a small random mesh, three loops, NaN-dropped points and one empty frame:
    the U-D engine gives the same x and P as the structured (Joseph) engine to 1e-9."""
    rng = np.random.default_rng(seed)
    model = small_model(rng, mesh=random_block_mesh(rng, n_interior=3), noise=1e-5, n_frames=6)
    y = simulate(model, rng, 1e-5)
    y[2, :3] = np.nan
    y[4] = np.nan
    out = {}
    for name in ("structured", "ud"):
        eng = ENGINES[name](model)
        x0, P = model.x0.copy(), model.P0.copy()
        nr = model.n_restart
        rows = []
        for loop in range(3):
            eng.reset(x0, P)
            rows.append(filter_loop(eng, model, y, loop))
            x0 = model.x0.copy()
            x0[nr:] = eng.x[nr:]
            P = model.P0.copy()
            P[nr:, nr:] = eng.P[nr:, nr:]
        out[name] = (np.array(rows), eng.P.copy())
    (xa, Pa), (xb, Pb) = out["structured"], out["ud"]
    assert _relmax(xb, xa) <= 1e-9
    assert _relmax(Pb, Pa) <= 1e-9


def test_ud_factors_stay_nonnegative_and_P_is_their_product():
    rng = np.random.default_rng(3)
    model = small_model(rng, mesh=random_block_mesh(rng, n_interior=2), noise=1e-5)
    y = simulate(model, rng, 1e-5)
    eng = UDEngine(model)
    eng.reset(model.x0, model.P0)
    for t in range(model.n_frames):
        if t > 0:
            eng.predict(t - 1)
        eng.update(y[t], t, np.ones(model.dim_obs, bool))
        U, d = eng.factors
        assert np.all(d >= 0)
        np.testing.assert_array_equal(np.tril(U, -1), 0.0)
        np.testing.assert_array_equal(eng.P, 0.5 * ((U * d) @ U.T + ((U * d) @ U.T).T))


def test_ud_cyclic_run_checkpoints_and_resumes_bit_identical(tmp_path, monkeypatch):
    rng = np.random.default_rng(11)
    model = small_model(rng, mesh=random_block_mesh(rng, n_interior=2), noise=1e-5, n_frames=5)
    y = simulate(model, rng, 1e-5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        full = cyclic_estimate(model, y, max_loops=4, tol=1e-12, engine="ud")
        ref = cyclic_estimate(model, y, max_loops=4, tol=1e-12, engine="structured")
        ckpt = str(tmp_path / "ud.npz")
        cyclic_estimate(model, y, max_loops=2, tol=1e-12, engine="ud", checkpoint=ckpt)
        assert int(load_checkpoint(ckpt)["loops_done"]) == 2
        loops = count_calls(monkeypatch, cyclic_module, "filter_loop")
        resumed = cyclic_estimate(model, y, max_loops=4, tol=1e-12, engine="ud", checkpoint=ckpt)
        assert len(loops) == 4 - 2                  # it went on from the checkpoint, not from the start
        # a checkpoint of the U-D run is not taken for a Joseph-form run
        with pytest.raises(ValueError, match="belongs to a different model or data set"):
            cyclic_estimate(model, y, max_loops=4, tol=1e-12, engine="structured", checkpoint=ckpt)
    assert resumed.loops == full.loops == 4
    np.testing.assert_array_equal(resumed.theta, full.theta)
    np.testing.assert_array_equal(resumed.P_theta, full.P_theta)
    np.testing.assert_array_equal(resumed.history.as_arrays()["x"], full.history.as_arrays()["x"])
    assert _relmax(full.theta, ref.theta) <= 1e-9
    assert _relmax(full.P_theta, ref.P_theta) <= 1e-9


def _kaminski(delta):
    """Kaminski, Bryson & Schmidt (1971): P0 = I, two almost identical, almost exact measurements
    (H = [[1, 1, 1], [1, 1, 1 + delta]], R = delta^2 I). The exact posterior has eigenvalues
    about 1, 0.75 and delta^2 / 6: condition number ~1e14 for delta = 1e-7."""
    H = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, 1.0 + delta]])
    model = LinearGaussianModel(np.eye(3), H, np.zeros((3, 3)), delta ** 2 * np.eye(2), np.zeros(3), np.eye(3), 2)
    mp.mp.dps = 60
    Hm, Pm = mp.matrix(H.tolist()), mp.eye(3)
    S = Hm * Pm * Hm.T + mp.eye(2) * mp.mpf(delta) ** 2
    exact = np.array(((mp.eye(3) - Pm * Hm.T * S ** -1 * Hm) * Pm).tolist(), dtype=float)
    return model, exact


def test_ud_keeps_definiteness_where_the_covariance_form_loses_it():
    """delta = 1e-7: the Joseph-form engine returns a P with an eigenvalue of about -2e-7
    (indefinite far beyond round-off; the exact one is +2e-15) and 2e-3 relative error; the
    U-D engine matches the 60-digit reference to 1e-8 with d >= 0. At delta = 1e-9 S itself
    is numerically singular: the covariance form fails, the U-D form is still right."""
    y = np.array([1.0, 1.0])
    model, exact = _kaminski(1e-7)
    assert np.linalg.cond(exact) > 1e13
    joseph = ENGINES["structured"](model)
    joseph.reset(model.x0, model.P0)
    joseph.update(y, 0, np.ones(2, bool))
    assert np.linalg.eigvalsh(joseph.P).min() < -1e-9
    assert _relmax(joseph.P, exact) > 1e-4
    ud = UDEngine(model)
    ud.reset(model.x0, model.P0)
    ud.update(y, 0, np.ones(2, bool))
    U, d = ud.factors
    assert np.all(d >= 0)
    assert _relmax(ud.P, exact) < 1e-8
    assert np.linalg.eigvalsh(ud.P).min() > -1e-15

    model, exact = _kaminski(1e-9)
    joseph = ENGINES["structured"](model)
    joseph.reset(model.x0, model.P0)
    with pytest.raises(np.linalg.LinAlgError):
        joseph.update(y, 0, np.ones(2, bool))
    ud = UDEngine(model)
    ud.reset(model.x0, model.P0)
    ud.update(y, 0, np.ones(2, bool))
    assert np.all(ud.factors[1] >= 0)
    assert _relmax(ud.P, exact) < 1e-8


def test_correlated_R_is_whitened():
    """A non-diagonal R: the U-D engine whitens by its Cholesky factor and matches the Joseph form."""
    rng = np.random.default_rng(2)
    A = np.array([[0.9, 0.2, 0.0], [0.0, 0.8, 0.1], [0.1, 0.0, 0.7]])
    H = rng.standard_normal((2, 3))
    R = np.array([[0.5, 0.3], [0.3, 0.4]])
    model = LinearGaussianModel(A, H, np.diag([0.1, 0.0, 0.2]), R, np.zeros(3), np.eye(3), 6)
    y = rng.standard_normal((6, 2))
    y[3, 1] = np.nan
    res = {}
    for name in ("structured", "ud"):
        eng = ENGINES[name](model)
        eng.reset(model.x0, model.P0)
        res[name] = (filter_loop(eng, model, y, safeguards=Safeguards()), eng.P)
    assert _relmax(res["ud"][0], res["structured"][0]) < 1e-12
    assert _relmax(res["ud"][1], res["structured"][1]) < 1e-12
