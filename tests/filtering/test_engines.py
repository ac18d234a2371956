"""Filtering with the model: filterpy plug-in, structured engine, cyclic loops, checkpoints."""
import numpy as np
import pytest
from helpers import count_calls, random_block_mesh, small_model
from helpers import simulate as _simulate
from hypothesis import given, settings
from hypothesis import strategies as st

import sfem_filters.filtering.cyclic as cyclic_module
from sfem_filters.benchmark.pinned import benchmark_model, pinned_benchmark
from sfem_filters.filtering import (
    ENGINES,
    SFEMExtendedKalmanFilter,
    cyclic_estimate,
    filter_loop,
    load_checkpoint,
)


@pytest.fixture(scope="module")
def bench():
    return pinned_benchmark(0)


def test_filterpy_and_structured_engines_agree(bench):
    """The library's own loop gives filterpy's x and P (joint EKF, pinned benchmark, one loop)."""
    model = benchmark_model(bench, "joint_ekf")
    out = {}
    for name in ("filterpy", "structured"):
        eng = ENGINES[name](model)
        eng.reset(model.x0, model.P0)
        states = filter_loop(eng, model, bench.observations)
        out[name] = (states, eng.P.copy())
    (xa, Pa), (xb, Pb) = out["filterpy"], out["structured"]
    assert np.abs(xa - xb).max() <= 1e-10 * np.abs(xa).max()
    assert np.abs(Pa - Pb).max() <= 1e-10 * np.abs(Pa).max()


def test_engines_agree_over_several_cyclic_loops(bench):
    """Three loops of the joint EKF: same material estimate and covariance from both engines."""
    model = benchmark_model(bench, "joint_ekf")
    with pytest.warns(RuntimeWarning, match="did not converge"):
        a = cyclic_estimate(model, bench.observations, max_loops=3, tol=1e-12, engine="filterpy")
    with pytest.warns(RuntimeWarning, match="did not converge"):
        b = cyclic_estimate(model, bench.observations, max_loops=3, tol=1e-12, engine="structured")
    assert np.abs(a.theta - b.theta).max() <= 1e-10 * np.abs(a.theta).max()
    assert np.abs(a.P_theta - b.P_theta).max() <= 1e-9 * np.abs(a.P_theta).max()
    np.testing.assert_allclose(a.states, b.states, rtol=0, atol=1e-10 * np.abs(a.states).max())


def test_predict_update_goes_through_the_model(bench):
    """filterpy's predict_update must use fx (not F x with F = I)."""
    model = benchmark_model(bench, "perfect_kf")
    a, b = model.make_ekf(), model.make_ekf()
    for t in range(3):
        y = bench.observations[t].reshape(-1, 1)
        if t == 0:
            a.update(y, model.H_jacobian, model.hx, args=t, hx_args=t)
            b.update(y, model.H_jacobian, model.hx, args=t, hx_args=t)
            continue
        a.predict(u=t - 1)
        a.update(y, model.H_jacobian, model.hx, args=t, hx_args=t)
        b.predict_update(y, model.H_jacobian, model.hx, args=t, hx_args=t, u=t - 1)
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-15)


def test_hand_driven_filterpy_ekf_equals_cyclic_estimate(bench):
    """The documented user loop on filterpy's EKF reproduces cyclic_estimate's single KF loop."""
    model = benchmark_model(bench, "perfect_kf")
    ekf = model.make_ekf()
    assert isinstance(ekf, SFEMExtendedKalmanFilter)
    xs = []
    for t, y in enumerate(bench.observations):
        if t > 0:
            ekf.predict(u=t - 1)
        ekf.update(y.reshape(-1, 1), model.H_jacobian, model.hx, args=t, hx_args=t)
        xs.append(ekf.x.ravel().copy())
    res = cyclic_estimate(model, bench.observations, engine="structured")
    assert res.loops == 1 and res.converged
    np.testing.assert_allclose(np.array(xs), res.states, rtol=0, atol=1e-12 * np.abs(res.states).max())


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), noise=st.floats(1e-6, 1e-4), engine=st.sampled_from(["structured", "filterpy"]))
def test_covariance_stays_symmetric_positive_definite(seed, noise, engine):
    """Random meshes, materials and noise: P is SPD after every predict and update, over 3 loops."""
    rng = np.random.default_rng(seed)
    model = small_model(rng, mesh=random_block_mesh(rng, n_interior=int(rng.integers(2, 8))), noise=noise)
    y = _simulate(model, rng, noise)
    eng = ENGINES[engine](model)
    x0, P = model.x0.copy(), model.P0.copy()
    nx = model.dim_x
    for loop in range(3):
        eng.reset(x0, P)
        for t in range(model.n_frames):
            if t > 0:
                eng.predict(t - 1)
                _assert_spd(eng.P)
            eng.update(y[t], t, np.ones(model.dim_obs, bool))
            _assert_spd(eng.P)
            assert np.all(np.isfinite(eng.x))
        x0 = model.x0.copy()
        x0[nx:] = eng.x[nx:]
        P = model.P0.copy()
        P[nx:, nx:] = eng.P[nx:, nx:]


def _assert_spd(P):
    """Symmetric to round-off on the scale of each entry, and positive definite.

    The diagonal spans many orders of magnitude (m^2, (m/s)^2, material), so both checks are
    made on the correlation form C = S^-1/2 P S^-1/2, S = diag(P)."""
    d = np.sqrt(np.diag(P))
    assert np.all(d > 0)
    C = P / np.outer(d, d)
    assert np.abs(C - C.T).max() <= 1e-9
    lam = np.linalg.eigvalsh(0.5 * (C + C.T))
    assert lam.min() > 0, lam.min()


@pytest.mark.filterwarnings("ignore:cyclic_estimate")
def test_material_covariance_shrinks_and_estimate_improves():
    """On noise-free-ish data from a non-uniform material the joint EKF moves toward it."""
    rng = np.random.default_rng(21)
    mesh = random_block_mesh(rng)
    from sfem_filters.fem.material import Material
    true = Material(np.where(mesh.centroids[:, 0] > 0.01, 1.2e5, 6e4), np.full(mesh.n_elements, 0.4))
    truth_model = small_model(np.random.default_rng(3), mesh=mesh, material=true, parameterisation=None, n_frames=12)
    y = _simulate(truth_model, rng, 1e-7)
    start = Material.uniform(mesh.n_elements, 8.5e4, 0.4)
    model = small_model(np.random.default_rng(3), mesh=mesh, material=start, n_frames=12, noise=1e-7)
    res = cyclic_estimate(model, y, max_loops=15, tol=1e-3)
    est = model.material_of_theta(res.theta)
    err_before = np.mean(np.abs(start.E - true.E) / true.E)
    err_after = np.mean(np.abs(est.E - true.E) / true.E)
    assert err_after < 0.5 * err_before
    assert np.all(np.diag(res.P_theta) < np.diag(model.P0)[model.dim_x:])


def test_missing_observations_are_dropped_not_zeroed(bench):
    """A NaN row is left out of its update; an all-NaN frame is predict-only."""
    model = benchmark_model(bench, "perfect_kf")
    y = bench.observations.copy()
    y[5] = np.nan
    y[7, :4] = np.nan
    res = cyclic_estimate(model, y)
    h = res.history.as_arrays()
    assert h["n_obs"][5] == 0 and np.isnan(h["nis"][5]) and np.all(np.isnan(h["innovation"][5]))
    assert h["n_obs"][7] == model.dim_obs - 4
    # frame 5 posterior is the prior: propagate frame 4 by hand
    np.testing.assert_allclose(res.states[5], model.fx(res.states[4], 4), atol=1e-15)
    # the partially observed frame equals an update with the observed rows only
    eng = ENGINES["filterpy"](model)
    eng.reset(model.x0, model.P0)
    full = filter_loop(eng, model, y)
    np.testing.assert_allclose(full, res.states, atol=1e-12 * np.abs(full).max())
    with pytest.raises(ValueError, match="observations: expected finite values or NaN"):
        cyclic_estimate(model, np.where(np.isnan(y), np.inf, y))
    with pytest.raises(ValueError, match=r"observations: expected shape \(16, 26\)"):
        cyclic_estimate(model, y[:, :3])


def test_checkpoint_resume_is_bit_identical(tmp_path, bench, monkeypatch):
    """Stopping after 3 loops and resuming ends exactly as the uninterrupted run, running only the 2 loops left."""
    model = benchmark_model(bench, "joint_ekf")
    with pytest.warns(RuntimeWarning, match="did not converge"):
        full = cyclic_estimate(model, bench.observations, max_loops=5, tol=1e-12)
    ckpt = tmp_path / "run.npz"
    with pytest.warns(RuntimeWarning, match="did not converge"):
        cyclic_estimate(benchmark_model(bench, "joint_ekf"), bench.observations, max_loops=3, tol=1e-12,
                        checkpoint=str(ckpt))
    assert int(load_checkpoint(ckpt)["loops_done"]) == 3
    loops = count_calls(monkeypatch, cyclic_module, "filter_loop")
    with pytest.warns(RuntimeWarning, match="did not converge"):
        resumed = cyclic_estimate(benchmark_model(bench, "joint_ekf"), bench.observations, max_loops=5,
                                  tol=1e-12, checkpoint=str(ckpt))
    assert len(loops) == 5 - 3                      # it went on from the checkpoint, not from the start
    assert resumed.loops == full.loops == 5
    np.testing.assert_array_equal(resumed.theta, full.theta)
    np.testing.assert_array_equal(resumed.P_theta, full.P_theta)
    np.testing.assert_array_equal(resumed.states, full.states)
    np.testing.assert_array_equal(resumed.history.as_arrays()["x"], full.history.as_arrays()["x"])


def test_checkpoint_errors_are_clear(tmp_path, bench):
    model = benchmark_model(bench, "joint_ekf")
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(ValueError, match="is not a readable checkpoint"):
        cyclic_estimate(model, bench.observations, max_loops=1, checkpoint=str(bad))
    ckpt = tmp_path / "other.npz"
    with pytest.warns(RuntimeWarning):
        cyclic_estimate(model, bench.observations, max_loops=1, tol=1e-12, checkpoint=str(ckpt))
    other = bench.observations + 1e-6
    with pytest.raises(ValueError, match="belongs to a different model or data set"):
        cyclic_estimate(benchmark_model(bench, "joint_ekf"), other, max_loops=2, checkpoint=str(ckpt))
    # a different model on the same data: another strategy, or the same one with other damping
    kf = tmp_path / "kf.npz"
    cyclic_estimate(benchmark_model(bench, "uniform_kf"), bench.observations, checkpoint=str(kf))
    with pytest.raises(ValueError, match="belongs to a different model or data set"):
        cyclic_estimate(benchmark_model(bench, "perfect_kf"), bench.observations, checkpoint=str(kf))
    damped = benchmark_model(bench, "uniform_kf")
    damped.alpha = 20.0
    with pytest.raises(ValueError, match="belongs to a different model or data set"):
        cyclic_estimate(damped, bench.observations, checkpoint=str(kf))
    resumed = cyclic_estimate(benchmark_model(bench, "uniform_kf"), bench.observations, checkpoint=str(kf))
    assert resumed.converged and resumed.loops == 1


def test_argument_errors(bench):
    model = benchmark_model(bench, "perfect_kf")
    with pytest.raises(ValueError, match="engine: expected one of"):
        cyclic_estimate(model, bench.observations, engine="fast")
    with pytest.raises(ValueError, match="max_loops: expected an integer >= 1"):
        cyclic_estimate(model, bench.observations, max_loops=0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), nx=st.integers(1, 12), p=st.integers(0, 6),
       scale=st.floats(1e-8, 1e4))
def test_factored_propagation_equals_the_plain_product(seed, nx, p, scale):
    """G G^T with G = [A L_xx + Mt L_tx, Mt L_tt] is [A Mt] P [A Mt]^T (the structured time
    update's kinematic block), for random PD P of any scale, with and without parameters;
    without a factor (P not positive definite) the plain product is used."""
    from sfem_filters.filtering.structured import propagate_factored
    rng = np.random.default_rng(seed)
    n = nx + p
    X = rng.standard_normal((n, n + 2))
    P = scale * (X @ X.T)
    F = rng.standard_normal((nx, n))
    A, Mt = F[:, :nx], F[:, nx:]
    ref = F @ P @ F.T
    got = propagate_factored(A, Mt, P, np.linalg.cholesky(P), nx)
    tol = 1e-12 * np.abs(F).max() ** 2 * np.abs(P).max() * n
    np.testing.assert_allclose(got, ref, rtol=0, atol=tol)
    assert np.array_equal(got, got.T)
    np.testing.assert_allclose(propagate_factored(A, Mt, P, None, nx), ref, rtol=0, atol=tol)


def test_structured_engine_reuses_the_checked_factor_and_falls_back_without_one(bench):
    """The factor Safeguards computes is the one the next predict uses; a P that is not
    positive definite (zero variance of one state) still predicts, by the plain product."""
    from sfem_filters.filtering import Safeguards, StructuredEngine
    model = benchmark_model(bench, "joint_ekf")
    eng = StructuredEngine(model)
    eng.update(bench.observations[0], 0, np.ones(model.dim_obs, bool))
    Safeguards().check_covariance(eng, 0, 0)
    L = eng.cholesky()
    np.testing.assert_allclose(L @ L.T, eng.P, rtol=0, atol=1e-13 * np.abs(eng.P).max())
    assert eng.cholesky() is L                     # cached until P changes
    eng.predict(0)
    assert eng.cholesky() is not L
    assert np.array_equal(eng.P, eng.P.T)          # kept exactly symmetric by every step
    eng.update(bench.observations[1], 1, np.ones(model.dim_obs, bool))
    assert np.array_equal(eng.P, eng.P.T)
    P = eng.P.copy()
    P[0, :] = P[:, 0] = 0.0
    eng.reset(eng.x, P)
    assert eng.cholesky() is None
    F = model.F_jacobian(eng.x, 1)
    eng.predict(1)
    assert np.array_equal(eng.P, eng.P.T)
    Q = model.Q
    np.testing.assert_allclose(eng.P, F @ P @ F.T + Q, rtol=0, atol=1e-12 * np.abs(eng.P).max())


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(1, 15), m=st.integers(1, 6), optimal=st.booleans())
def test_joseph_update_equals_the_textbook_form(seed, n, m, optimal):
    """P + X + X^T with X = K (K S / 2 - P H^T)^T is (I - KH) P (I - KH)^T + K R K^T for any
    gain (optimal or not), and exactly symmetric."""
    from sfem_filters.filtering import joseph_update
    rng = np.random.default_rng(seed)
    X = rng.standard_normal((n, n + 1))
    P = X @ X.T
    H = rng.standard_normal((m, n)) * (rng.random((m, n)) < 0.5)
    R = np.diag(rng.uniform(0.1, 2.0, m))
    S = H @ P @ H.T + R
    K = P @ H.T @ np.linalg.inv(S) if optimal else rng.standard_normal((n, m))
    IKH = np.eye(n) - K @ H
    ref = IKH @ P @ IKH.T + K @ R @ K.T
    got = joseph_update(P, K, P @ H.T, S)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10 * max(np.abs(ref).max(), np.abs(P).max()))
    assert np.array_equal(got, got.T)
