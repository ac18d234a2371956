"""The RTS smoother of a linearised model and the iterated (Gauss-Newton, damped) smoother (issue 13)."""
import os
import warnings

import numpy as np
import pytest
import scipy.sparse as sp
from helpers import bias_model, count_calls
from hypothesis import given, settings
from hypothesis import strategies as st

import sfem_filters.fem.modal_stiffness as modal_stiffness_module
import sfem_filters.filtering.gauss_newton as gauss_newton_module
import sfem_filters.model as model_module
from sfem_filters import fem
from sfem_filters.benchmark.pinned import benchmark_model, pinned_benchmark
from sfem_filters.cardiac import annulus_sequence, build_model, prepare
from sfem_filters.fem import Parameterisation
from sfem_filters.filtering import (
    CyclicEKF,
    IteratedSmoother,
    LinearGaussianModel,
    LinearisedModel,
    MapObjective,
    laplace_check,
    linearise,
    linearise_dense,
    load_checkpoint,
    one_cycle_covariance,
    rts_reference,
    smooth,
    smooth_backward,
    with_covariance,
)
from sfem_filters.filtering.iterated import open_loop, step_in_sd
from sfem_filters.filtering import memory as memory_module
from sfem_filters.filtering import smoother as smoother_module
from sfem_filters.filtering.smoother import (
    PEAK_FACTOR,
    WORKING,
    check_memory,
    covariance_interval,
    kalman_forward,
    stored_bytes,
)


def _spd(rng, k, scale=1.0):
    X = rng.standard_normal((k, k))
    return scale * (X @ X.T / k + 0.1 * np.eye(k))


def _random_linearised(rng, nr, p, m, T, sparse):
    A = [rng.standard_normal((nr, nr)) * 0.4 for _ in range(T - 1)]
    if sparse:
        A = [sp.csr_matrix(a) for a in A]
    return LinearisedModel(A=A, M=rng.standard_normal((T - 1, nr, p)), c=rng.standard_normal((T - 1, nr)),
                           H=rng.standard_normal((m, nr)), R=np.array([_spd(rng, m, 0.1) for _ in range(T)]),
                           Q=_spd(rng, nr, 0.05), xi0=rng.standard_normal(nr), P0=_spd(rng, nr),
                           theta_bar=rng.standard_normal(p), theta0=rng.standard_normal(p), P_theta0=_spd(rng, p))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), nr=st.integers(1, 6), p=st.integers(0, 3), m=st.integers(1, 4),
       T=st.integers(2, 7), sparse=st.booleans(), missing=st.floats(0.0, 0.5))
def test_modified_bryson_frazier_equals_the_textbook_rts(seed, nr, p, m, T, sparse, missing):
    """Smoothed means, the parameters' covariance and the variances of output operators: the
    O(n^2)-per-frame backward pass gives the textbook RTS smoother's numbers (Cholesky-solved
    gains), with missing rows and empty frames."""
    rng = np.random.default_rng(seed)
    lin = _random_linearised(rng, nr, p, m, T, sparse)
    y = rng.standard_normal((T, m))
    y[rng.uniform(size=y.shape) < missing] = np.nan
    L = rng.standard_normal((3, nr))
    L[:, 0] = 0.0                                     # an output that reads part of the state only
    sm = smooth(lin, y, outputs={"L": L, "all": np.eye(nr)}, covariance=True)
    xs, Ps = rts_reference(lin, y)
    scale = max(np.abs(xs).max(), 1.0)
    assert np.abs(sm.smoothed - xs).max() <= 1e-9 * scale
    np.testing.assert_allclose(sm.P_theta, Ps[0][nr:, nr:], rtol=1e-8, atol=1e-12)
    vL = np.array([np.diag(L @ P[:nr, :nr] @ L.T) for P in Ps])
    vI = np.array([np.diag(P[:nr, :nr]) for P in Ps])
    np.testing.assert_allclose(sm.variances["L"], vL, rtol=1e-7, atol=1e-10 * vL.max())
    np.testing.assert_allclose(sm.variances["all"], vI, rtol=1e-7, atol=1e-10 * vI.max())
    assert np.ptp(sm.smoothed[:, nr:], axis=0).max(initial=0.0) <= 1e-9 * scale     # theta is static


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), nr=st.integers(1, 6), p=st.integers(0, 3), m=st.integers(1, 4),
       T=st.integers(2, 7), sparse=st.booleans(), missing=st.floats(0.0, 0.8))
def test_means_from_the_gains_alone_equal_the_textbook_rts(seed, nr, p, m, T, sparse, missing):
    """A pass that keeps no covariance of any frame (``store="mean"``: gains and innovations
    only) smooths the means by the disturbance smoother, forward from the smoothed initial state
    under the smoothed process noise: the textbook RTS means and the same theta and covariance of
    theta, with missing rows and empty frames; it keeps no n x n matrix a frame, and refuses to
    give covariances."""
    rng = np.random.default_rng(seed)
    lin = _random_linearised(rng, nr, p, m, T, sparse)
    y = rng.standard_normal((T, m))
    y[rng.uniform(size=y.shape) < missing] = np.nan
    fwd = kalman_forward(lin, y, store="mean")
    sm = smooth_backward(lin, fwd)
    xs, Ps = rts_reference(lin, y)
    scale = max(np.abs(xs).max(), 1.0)
    assert np.abs(sm.smoothed - xs).max() <= 1e-9 * scale
    np.testing.assert_allclose(sm.theta, xs[0, nr:], rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(sm.P_theta, Ps[0][nr:, nr:], rtol=1e-8, atol=1e-12)
    assert not fwd.engine.priors and sm.variances == {}
    full = smooth(lin, y)                                  # no covariance asked: the means' store
    assert full.forward.engine.store == "mean"
    np.testing.assert_array_equal(full.smoothed, sm.smoothed)
    with pytest.raises(ValueError, match="covariance=True needs a pass run with store='covariance'"):
        smooth_backward(lin, fwd, outputs={"all": np.eye(nr)}, covariance=True)
    with pytest.raises(ValueError, match="store: expected one of"):
        kalman_forward(lin, y, store="everything")
    with pytest.raises(ValueError, match="every: expected an integer >= 1"):
        kalman_forward(lin, y, every=0)
    with pytest.raises(ValueError, match="expected a pass run with store='covariance' or 'mean'"):
        smooth_backward(lin, kalman_forward(lin, y, store=False))


@pytest.mark.parametrize("nr, p, m, T", [(9, 2, 1, 6), (3, 1, 3, 6), (6, 1, 2, 5)])
def test_information_factor_and_its_switch_to_dense_give_the_textbook_variances(nr, p, m, T, monkeypatch):
    """The backward pass keeps Lambda as a factor W W^T while its rank (the rows observed from
    the frame on) stays below n, and switches to the dense recursion when it would not: the
    whole pass factored (9 + 2 states, 6 rows), dense from the second observed frame on (3 + 1
    states, 3 rows a frame), and switching midway give the textbook RTS variances."""
    rng = np.random.default_rng(nr * 100 + m)
    lin = _random_linearised(rng, nr, p, m, T, sparse=False)
    y = rng.standard_normal((T, m))
    factored = []
    step = smoother_module._transpose_columns
    monkeypatch.setattr(smoother_module, "_transpose_columns", lambda *a: factored.append(1) or step(*a))
    sm = smooth(lin, y, outputs={"all": np.eye(nr)}, covariance=True)
    n = nr + p
    assert len(factored) == sum(1 for t in range(1, T) if (T - t) * m < n)   # frames carried back as a factor
    _, Ps = rts_reference(lin, y)
    vI = np.array([np.diag(P[:nr, :nr]) for P in Ps])
    np.testing.assert_allclose(sm.variances["all"], vI, rtol=1e-8, atol=1e-11 * vI.max())


class _Repair:
    """A safeguard that changes P at chosen frames, as a real repair would (and records it)."""

    def __init__(self, frames):
        self.frames, self.repairs = set(frames), []

    def check_covariance(self, engine, loop, t):
        if t in self.frames:
            engine.reset(engine.x, engine.P + 0.3 * np.eye(len(engine.x)))
            self.repairs.append((loop, t))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), nr=st.integers(1, 5), p=st.integers(0, 2), m=st.integers(1, 3),
       T=st.integers(2, 8), missing=st.floats(0.0, 0.6), repaired=st.sets(st.integers(0, 7), max_size=3))
def test_means_across_a_repair_equal_the_covariance_pass(seed, nr, p, m, T, missing, repaired):
    """A safeguard's repair D of a frame's covariance breaks the disturbance smoother's step; the
    pass for means records D and steps from x_t|T - D lambda_t: the covariance pass's means."""
    rng = np.random.default_rng(seed)
    lin = _random_linearised(rng, nr, p, m, T, sparse=bool(seed % 2))
    y = rng.standard_normal((T, m))
    y[rng.uniform(size=y.shape) < missing] = np.nan
    full = smooth(lin, y, covariance=True, every=1, safeguards=_Repair(repaired))
    mean = smooth(lin, y, safeguards=_Repair(repaired))
    assert mean.forward.engine.store == "mean"
    scale = max(np.abs(full.smoothed).max(), 1.0)
    assert np.abs(mean.smoothed - full.smoothed).max() <= 1e-9 * scale


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), nr=st.integers(1, 5), p=st.integers(0, 2), m=st.integers(1, 3),
       T=st.integers(2, 9), every=st.integers(2, 10), missing=st.floats(0.0, 0.6),
       repaired=st.sets(st.integers(0, 8), max_size=3))
def test_checkpointed_covariance_pass_gives_the_same_numbers(seed, nr, p, m, T, every, missing, repaired):
    """Keeping the prior covariance of every k-th frame only and recomputing the others in the
    backward pass, a segment at a time, gives every mean and variance of the pass that keeps them
    all (the same arithmetic: equal to round-off, which BLAS kernels may vary with memory
    alignment), also across frames where a safeguard changed P; it keeps ceil(T / k)."""
    rng = np.random.default_rng(seed)
    lin = _random_linearised(rng, nr, p, m, T, sparse=bool(seed % 2))
    y = rng.standard_normal((T, m))
    y[rng.uniform(size=y.shape) < missing] = np.nan
    outputs = {"all": np.eye(nr), "L": rng.standard_normal((2, nr))}
    full = smooth(lin, y, outputs=outputs, covariance=True, every=1, safeguards=_Repair(repaired))
    part = smooth(lin, y, outputs=outputs, covariance=True, every=every, safeguards=_Repair(repaired))
    assert len(full.forward.engine.priors) == T
    assert sorted(part.forward.engine.priors) == list(range(0, T, every))
    np.testing.assert_allclose(part.smoothed, full.smoothed, rtol=1e-12, atol=1e-12 * np.abs(full.smoothed).max())
    for name in outputs:
        v = full.variances[name]
        np.testing.assert_allclose(part.variances[name], v, rtol=1e-10, atol=1e-12 * np.abs(v).max())
    np.testing.assert_array_equal(part.P_theta, full.P_theta)             # the forward pass's own


def test_covariance_interval_keeps_every_frame_where_they_fit():
    """One prior covariance a frame where the pass fits with head-room, else ceil(sqrt(T))
    checkpoints and a segment of at most k - 1 recomputed; gains counted either way."""
    n, T = 1000, 24
    full, working = stored_bytes(n, T), 8.0 * WORKING * n ** 2
    assert full == 8.0 * T * n ** 2
    assert covariance_interval(n, T, available=PEAK_FACTOR * (full + working)) == 1
    k = covariance_interval(n, T, available=PEAK_FACTOR * (full + working) - 1.0)
    assert k == 5                                               # ceil(sqrt(24))
    assert stored_bytes(n, T, k) == 8.0 * (5 + 4) * n ** 2     # 5 checkpoints, a segment of 4 recomputed
    assert stored_bytes(n, 3, 10) == 8.0 * (1 + 2) * n ** 2    # fewer frames than the interval
    assert stored_bytes(n, T, None, observed=100) == 8.0 * 100 * n     # a pass for means: its gains
    assert stored_bytes(n, T, 1, observed=100) == full + 8.0 * 100 * n
    assert covariance_interval(n, 1, available=0.0) == 1       # nothing to recompute
    assert covariance_interval(n, 2, available=0.0) == 2


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), nr=st.integers(2, 7), p=st.integers(0, 2), T=st.integers(2, 5),
       n_outputs=st.integers(1, 4))
def test_output_blocks_give_the_textbook_variances(seed, nr, p, T, n_outputs):
    """Outputs with structure (rows reading disjoint column sets, rows repeated across outputs,
    rows of zeros, an output spread over several blocks): split into blocks with disjoint
    columns, every row computed once per distinct row, the variances are the textbook RTS
    smoother's."""
    rng = np.random.default_rng(seed)
    lin = _random_linearised(rng, nr, p, 2, T, False)
    y = rng.standard_normal((T, 2))
    split = rng.integers(1, nr)                       # columns [0, split) and [split, nr)
    pool = []
    for _ in range(4):
        row = rng.standard_normal(nr)
        row[split:] = 0.0 if rng.uniform() < 0.5 else row[split:]
        row[:split] = 0.0 if rng.uniform() < 0.3 else row[:split]
        pool.append(row)
    pool.append(np.zeros(nr))
    outputs = {f"o{k}": np.array([pool[i] for i in rng.integers(0, len(pool), size=rng.integers(1, 6))])
               for k in range(n_outputs)}
    blocks = smoother_module._output_blocks(outputs)
    seen_cols = np.concatenate([cols for cols, _, _ in blocks]) if blocks else np.zeros(0, int)
    assert len(seen_cols) == len(np.unique(seen_cols))                  # disjoint columns
    for name, L in outputs.items():
        where = np.concatenate([w for _, _, members in blocks for n, w, _ in members if n == name] or [[]])
        assert np.array_equal(np.sort(where.astype(int)), np.flatnonzero(np.any(L != 0, axis=1)))
        for cols, rows, members in blocks:                              # every row rebuilt from its block
            for n, w, which in members:
                if n == name:
                    assert np.array_equal(rows[which], L[np.ix_(w, cols)])
                    assert not np.any(np.delete(L[w], cols, axis=1))
    outputs["none"] = np.zeros((0, nr))                # an output without rows, and one given sparse
    outputs["sparse"] = sp.csr_matrix(outputs["o0"])
    sm = smooth(lin, y, outputs=outputs, covariance=True)
    _, Ps = rts_reference(lin, y)
    assert sm.variances["none"].shape == (T, 0)
    for name, L in outputs.items():
        L = L.toarray() if sp.issparse(L) else L
        want = np.array([np.diag(L @ P[:nr, :nr] @ L.T) for P in Ps]).reshape(T, -1)
        np.testing.assert_allclose(sm.variances[name], want, rtol=1e-7, atol=1e-10 * max(want.max(initial=0.0), 1e-300))
    with pytest.raises(ValueError, match=rf"^outputs: expected \(k, {nr}\) matrices on xi, got 'row' with shape"):
        smooth(lin, y, outputs={"row": np.ones(nr)}, covariance=True)


@pytest.fixture(scope="module")
def pinned():
    return pinned_benchmark(0)


def test_modal_linearisation_equals_the_dense_jacobians(pinned):
    """The SFEM model's own linearisation (modal coordinates, sparse transition) and the generic
    one (F_jacobian at every frame) are the same linear-Gaussian model: same smoothed trajectory,
    covariance of theta, displacement variances and log-likelihood."""
    m = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    z = np.tile(m.x0, (m.n_frames, 1))
    z[:, : m.dim_x] += 1e-4 * np.random.default_rng(1).standard_normal((m.n_frames, m.dim_x))
    out = {}
    for name, lin in (("modal", m.linearise(z)), ("dense", linearise_dense(m, z))):
        assert (lin.V is None) == (name == "dense")
        u = lin.output_in_xi(m.output_operators()["displacement"])
        sm = smooth(lin, pinned.observations, covariance=True, outputs={"u": u})
        out[name] = (lin.to_model(sm.smoothed[:, : m.n_restart]), sm.P_theta, sm.variances["u"], sm.log_likelihood)
    a, b = out["modal"], out["dense"]
    assert np.abs(a[0] - b[0]).max() <= 1e-10 * np.abs(b[0]).max()
    np.testing.assert_allclose(a[1], b[1], rtol=1e-9)
    np.testing.assert_allclose(a[2], b[2], rtol=1e-9)
    assert abs(a[3] - b[3]) <= 1e-9 * abs(b[3])


def test_profile_cost_is_the_map_cost_of_the_optimal_trajectory(pinned):
    """Completing the square: for a fixed theta the smallest MAP cost over the trajectory is half
    the filter's summed NIS plus theta's prior term, and the smoothed trajectory attains it."""
    m = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    nr = m.n_restart
    theta = m.x0[nr:] + np.array([0.1, -0.2, 0.5, 0.3])
    z = open_loop(m)
    z[:, nr:] = theta
    lin = linearise(m, z, sensitivity=False)
    assert lin.n_params == 0
    sm = smooth(lin, pinned.observations)
    z[:, :nr] = lin.to_model(sm.smoothed[:, :nr])
    d = theta - m.x0[nr:]
    profile = sm.fit + 0.5 * d @ np.linalg.solve(m.P0[nr:, nr:], d)
    objective = MapObjective(m, pinned.observations)
    assert abs(objective(z) - profile) <= 1e-8 * profile
    z2 = z.copy()
    z2[3, :nr] += 1e-6                                    # any other trajectory costs more
    assert objective(z2) > objective(z)


def test_linear_model_smoother_is_the_exact_posterior_and_one_cycle_correction_is_exact():
    """Linear in (x, theta): the smoother's posterior of theta is the exact one, which is the
    first cyclic loop's (undamped, one Gauss-Newton step is exact and the next one is zero); the carried covariance after k loops, corrected to one cycle, gives it
    back (the data-cloning correction is exact for a linear model)."""
    rng = np.random.default_rng(3)
    model, y = bias_model(rng, 3, 2, 2, 12)
    nr = model.n_restart
    res = IteratedSmoother(damping=0.0).run(model, y)      # undamped: the first Gauss-Newton step is exact
    one = CyclicEKF(max_loops=1).run(model, y)
    np.testing.assert_allclose(res.theta, one.theta, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.P_theta, one.P_theta, rtol=1e-9)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        five = CyclicEKF(max_loops=5, tol=1e-12).run(model, y)
    np.testing.assert_allclose(five.P_theta_one_cycle, one.P_theta, rtol=1e-8)
    np.testing.assert_allclose(one_cycle_covariance(model.P0[nr:, nr:], five.P_theta, 5), one.P_theta, rtol=1e-8)
    assert np.all(np.linalg.eigvalsh(five.P_theta) < np.linalg.eigvalsh(one.P_theta) + 1e-15)


def test_no_parameters_gives_the_rts_smoother():
    """A model without parameters needs no iteration: the result is the exact smoothed trajectory."""
    rng = np.random.default_rng(0)
    model, y = bias_model(rng, 3, 1, 2, 8)
    plain = LinearGaussianModel(model._A, model._Hx, model.Q[:3, :3], model.R, np.zeros(3), 0.1 * np.eye(3), 8)
    res = IteratedSmoother().run(plain, y)
    assert res.stop_reason == "no parameters" and res.converged and res.iterations == 0
    xs, _ = rts_reference(linearise_dense(plain, np.zeros((8, 3))), y)
    np.testing.assert_allclose(res.states, xs, rtol=1e-10, atol=1e-12)


def test_pinned_smoother_converges_with_falling_cost_and_matches_the_exact_marginal(pinned):
    """2-region map on the pinned benchmark: every accepted step lowers the MAP cost, the stop rule
    is met, and the joint mode and its Gauss-Newton covariance agree with the exact marginal
    posterior's MAP and Laplace covariance (one Kalman pass per theta) to about 1% of an sd."""
    m = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    res = IteratedSmoother().run(m, pinned.observations)
    costs = [r["cost"] for r in res.records]
    assert res.converged and res.stop_reason == "step" and len(costs) <= 10
    assert np.all(np.diff(costs) < 0) and all(r["decrease"] > 0 for r in res.records)
    check = laplace_check(m, pinned.observations, res.theta, res.P_theta)
    assert np.abs(check.z_mode).max() < 0.05
    assert np.abs(check.sd_ratio - 1).max() < 0.05
    assert check.kl < 0.01


def test_a_run_stopped_short_reports_its_estimate_in_the_history_too(pinned):
    """Stopped by the iteration limit far from the mode, the history (which the score tests and the
    effects' time courses read) carries the reported states and material, the point the final pass
    was linearised at, not that pass's unchecked Gauss-Newton step (many sd away here)."""
    m = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    res = IteratedSmoother(damping=1e8, max_damping=1e12, max_iterations=1).run(m, pinned.observations)
    assert not res.converged and res.stop_reason == "max_iterations"
    nr = m.n_restart
    x = np.asarray(res.history.x, float)
    np.testing.assert_array_equal(x, res.states)                    # kinematics too, not only the material
    np.testing.assert_array_equal(x[:, nr:], np.broadcast_to(res.theta, x[:, nr:].shape))
    assert res.records[-1]["full_step_sd"] > 10


def test_a_step_shortened_by_damping_does_not_end_the_run(pinned):
    """Started with a huge damping (1e8 prior precisions), the first step is tiny (below 0.1 sd)
    while the undamped step of the model is tens of sd: the run goes on to the default run's mode
    instead of stopping at the prior and calling it converged."""
    m = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    ref = IteratedSmoother().run(m, pinned.observations)
    res = IteratedSmoother(damping=1e8, max_damping=1e12, max_iterations=60).run(m, pinned.observations)
    first = res.records[0]
    assert first["step_sd"] < 0.1 and first["rel_change"] < 1e-3 and first["full_step_sd"] > 10
    assert res.converged and res.iterations > 1
    assert np.max(np.abs(res.theta - ref.theta) / np.sqrt(np.diag(ref.P_theta))) < 0.01
    # a warm start at the mode: the same mode (the cost is the same), in fewer iterations
    warm = IteratedSmoother().run(m, pinned.observations, start=ref.states)
    assert warm.converged and warm.iterations < ref.iterations
    assert np.max(np.abs(warm.theta - ref.theta) / np.sqrt(np.diag(ref.P_theta))) < 0.01
    with pytest.raises(ValueError, match=r"^start: expected shape \(16, "):
        IteratedSmoother().run(m, pinned.observations, start=ref.states[1:])


def test_damped_smoother_converges_where_undamped_gauss_newton_does_not():
    """A region map on an annulus whose motion holds an undeclared active stress (the misspecified
    baseline of the measured slice, in small): undamped Gauss-Newton (relinearise at each pass's
    own smoothed trajectory, accept every step) raises the MAP cost and oscillates; the damped
    smoother lowers it at every step and meets its stop rule."""
    seq = annulus_sequence("active_polar", n_frames=12, seed=0, amplitude=(0.3, -0.6))
    m, y = build_model(prepare(seq, 8), (), "penalty", "region")
    nr = m.n_restart
    objective = MapObjective(m, y)
    z = open_loop(m)
    costs = [objective(z)]
    for _ in range(4):
        lin = linearise(m, z)
        sm = smooth(lin, y)
        z = np.concatenate([lin.to_model(sm.smoothed[:, :nr]), np.tile(sm.theta, (m.n_frames, 1))], axis=1)
        costs.append(objective(z))
    assert costs[1] > 5 * costs[0] and min(costs[1:]) > costs[0]
    res = IteratedSmoother().run(m, y)
    assert res.converged
    assert np.all(np.diff([r["cost"] for r in res.records]) < 0)
    assert res.cost < costs[0] / 5


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), p=st.integers(1, 6), q=st.integers(1, 12))
def test_step_in_sd_does_not_depend_on_the_parameters_coordinates(seed, p, q):
    """Recombining the parameters (theta = T theta', so step = T step', P = T P' T^T and the
    physical rows J' = J T) leaves the step in sd of the physical quantities unchanged, and so does
    scaling a row; without rows it is the largest |step| / sd over the parameters."""
    rng = np.random.default_rng(seed)
    P = _spd(rng, p)
    step = rng.standard_normal(p)
    J = rng.standard_normal((q, p))
    J[rng.random(q) < 0.2] = 0.0                        # quantities theta does not move are left out
    T = rng.standard_normal((p, p)) + 3 * np.eye(p)
    Ti = np.linalg.inv(T)
    a = step_in_sd(step, P, J)
    b = step_in_sd(Ti @ step, Ti @ P @ Ti.T, sp.csr_matrix(J @ T))
    c = step_in_sd(step, P, np.diag(rng.uniform(0.1, 10, q)) @ J)
    assert b == pytest.approx(a, rel=1e-8) and c == pytest.approx(a, rel=1e-10)
    keep = np.any(J != 0, axis=1)
    want = max((abs(j @ step) / np.sqrt(j @ P @ j) for j in J[keep]), default=0.0)
    assert a == pytest.approx(want, rel=1e-10)
    assert step_in_sd(step, P) == pytest.approx(np.max(np.abs(step) / np.sqrt(np.diag(P))), rel=1e-12)
    with pytest.raises(ValueError, match=rf"^jacobian: expected {p} columns \(one per parameter\)"):
        step_in_sd(step, P, np.ones((q, p + 1)))
    with pytest.raises(ValueError, match=r"^P_theta: expected shape"):
        step_in_sd(step, np.eye(p + 1), J)


def test_stop_rule_does_not_depend_on_how_the_regions_are_numbered():
    """The relative-region map's contrasts depend on the order of the region labels; renumbered
    regions give the same MAP path, and now the same step/sd rows and stop, to round-off."""
    seq = annulus_sequence("active_polar", n_frames=10, seed=1, amplitude=(0.2, -0.4))
    setup = prepare(seq, 8)
    perm = np.random.default_rng(0).permutation(int(setup.regions.max()) + 1)
    runs = []
    for labels in (setup.regions, perm[setup.regions]):
        setup.regions = labels
        m, y = build_model(setup, (), "penalty", "region")
        runs.append(IteratedSmoother().run(m, y))
    a, b = runs
    assert a.iterations == b.iterations and a.stop_reason == b.stop_reason
    np.testing.assert_allclose([r["cost"] for r in a.records], [r["cost"] for r in b.records], rtol=1e-8)
    for key in ("step_sd", "full_step_sd"):
        np.testing.assert_allclose([r[key] for r in a.records], [r[key] for r in b.records], rtol=1e-5)


def test_extrapolated_steps_reach_the_same_mode_with_a_falling_cost():
    """Under a measured pressure (60 kPa annulus, the level's 1/E tail) some accepted full steps
    beat their predicted decrease where the model predicts little more; only such steps are
    doubled, and only while the cost falls. The run reaches the mode of the run without
    extrapolation, in no more iterations, with the cost falling at every iteration."""
    stub = prepare(annulus_sequence(None, n_frames=3, seed=0), 8)
    mat = fem.Material.uniform(stub.mesh.n_elements, 60e3, 0.45)
    setup = prepare(annulus_sequence(None, seed=0, n_frames=8, drive="pressure", material=mat), 8)
    m, y = build_model(setup, (), "pressure", "region")
    off = IteratedSmoother(max_iterations=80, covariance=False, max_extrapolation=1).run(m, y)
    on = IteratedSmoother(max_iterations=80, covariance=False).run(m, y)
    assert off.converged and on.converged and on.iterations <= off.iterations
    assert all(r["step_length"] <= 1 for r in off.records)
    extended = [r for r in on.records if r["step_length"] > 1]
    assert extended and all(r["step_length"] in (2, 4, 8) for r in extended)
    assert all(r["gain_ratio"] >= 1.25 and r["newton_decrement"] < 1.0 for r in extended)
    assert all(r["decrease"] > 0 for r in on.records)
    assert abs(on.cost - off.cost) < 1e-3
    k = m.parameterisation.level_index
    assert abs(on.theta[k] - off.theta[k]) < 0.05 * np.sqrt(off.P_theta[k, k])


def test_checkpoint_resumes_to_the_uninterrupted_result(pinned, tmp_path, monkeypatch):
    """Stopped after 2 iterations and resumed (a larger limit is a stopping rule, not part of the
    fingerprint): the same mode, covariance and records as one uninterrupted run, with fewer filter
    passes than it (the resumed run goes on from the checkpoint, not from the start); a checkpoint of
    another model is refused."""
    m = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    passes = count_calls(monkeypatch, gauss_newton_module, "profile_pass")
    full = IteratedSmoother().run(m, pinned.observations)
    n_full = len(passes)
    path = str(tmp_path / "smoother.npz")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        part = IteratedSmoother(max_iterations=2).run(m, pinned.observations, checkpoint=path)
    assert part.iterations == 2 and not part.converged and os.path.exists(path)
    assert int(load_checkpoint(path)["loops_done"]) == 2
    passes.clear()
    resumed = IteratedSmoother().run(m, pinned.observations, checkpoint=path)
    assert 0 < len(passes) < n_full, (len(passes), n_full)
    assert resumed.iterations == full.iterations
    np.testing.assert_array_equal(resumed.states, full.states)
    np.testing.assert_array_equal(resumed.P_theta, full.P_theta)
    assert [r["cost"] for r in resumed.records] == [r["cost"] for r in full.records]
    other = benchmark_model(pinned, "joint_ekf")
    with pytest.raises(ValueError, match="checkpoint: .* belongs to a different model or data set"):
        IteratedSmoother().run(other, pinned.observations, checkpoint=path)


@pytest.mark.parametrize("kwargs, match", [
    (dict(max_iterations=0), "max_iterations: expected an integer >= 1"),
    (dict(tol=0.0), "tol: expected a positive"),
    (dict(sd_tol=-1.0), "sd_tol: expected a positive"),
    (dict(cost_tol=0.0), "cost_tol: expected a positive"),
    (dict(damping=-1.0), "damping: expected a non-negative"),
    (dict(max_damping=0.0), "max_damping: expected a positive"),
    (dict(max_extrapolation=0.5), "max_extrapolation: expected a finite multiple >= 1"),
    (dict(max_extrapolation=float("inf")), "max_extrapolation: expected a finite multiple >= 1"),
    (dict(max_extrapolation=True), "max_extrapolation: expected a finite multiple >= 1"),
])
def test_bad_settings_are_named(kwargs, match):
    with pytest.raises(ValueError, match=match):
        IteratedSmoother(**kwargs)


def test_bad_inputs_are_named(pinned):
    m = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    with pytest.raises(ValueError, match=r"observations: expected shape \(16, 26\)"):
        IteratedSmoother().run(m, pinned.observations[:5])
    with pytest.raises(TypeError, match="model: expected a model with the members"):
        IteratedSmoother().run(object(), pinned.observations)
    est = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    est.Q = est.Q.copy()
    est.Q[-1, -1] = 1e-4
    with pytest.raises(ValueError, match="expected static parameters"):
        IteratedSmoother().run(est, pinned.observations)


def test_a_run_too_large_for_the_memory_is_refused_before_any_pass(pinned, monkeypatch):
    """A covariance pass keeps a prior covariance a frame, or checkpoints where those do not fit,
    every pass its gains and WORKING n x n matrices, a run without covariances nothing more.
    Beyond the available memory a named MemoryError says how much, beyond a PEAK_FACTOR share a
    warning."""
    n, T = 1000, 24
    working = 8.0 * WORKING * n ** 2
    full = stored_bytes(n, T) + working
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_memory(n, T, available=1.01 * PEAK_FACTOR * full)
    kept = (r"the smoother keeps a 1000 x 1000 covariance for one frame in 5 of 24, recomputing the others and "
            r"gains \(72 MB\) and works in 6 1000 x 1000 matrices \(48 MB; about 360 MB at the run's peak\)")
    with pytest.warns(RuntimeWarning, match=kept + r", while 240 MB are available: the run may run out of memory"):
        check_memory(n, T, available=2.0 * (stored_bytes(n, T, 5) + working))
    with pytest.raises(MemoryError, match="model: " + kept + r", more than the 60 MB available; reduce the state"):
        check_memory(n, T, available=0.5 * (stored_bytes(n, T, 5) + working))
    with warnings.catch_warnings():                             # the means alone fit where no covariance pass does
        warnings.simplefilter("error")
        check_memory(n, T, available=1.01 * PEAK_FACTOR * (working + 8.0 * 50 * n), covariance=False, observed=50)
    with pytest.raises(MemoryError, match=r"model: the smoother keeps no covariance of any frame \(means only\) "
                                          r"and gains \(0 MB\) and works in 6 1000 x 1000 matrices \(48 MB"):
        check_memory(n, T, available=0.5 * working, covariance=False, observed=50)
    with pytest.raises(MemoryError, match=r"1\.2 GB available"):
        check_memory(10_000, T, available=1.2e9)
    if os.path.exists("/proc/meminfo"):
        assert memory_module.available_memory() > 0
    m = benchmark_model(pinned, "joint_ekf", parameterisation=Parameterisation.per_region(pinned.middle))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        lean = IteratedSmoother(max_iterations=1, covariance=False).run(m, pinned.observations)
    need = stored_bytes(m.dim_state, m.n_frames, covariance_interval(m.dim_state, m.n_frames, 0.0))   # checkpoints
    monkeypatch.setattr(memory_module, "available_memory", lambda: 0.9 * need)
    with pytest.raises(MemoryError, match="model: the smoother keeps"):     # its covariance pass, made later
        with_covariance(m, pinned.observations, lean)
    passes = []
    monkeypatch.setattr(smoother_module, "kalman_forward", lambda *a, **k: passes.append(1))
    with pytest.raises(MemoryError, match="model: the smoother keeps"):
        IteratedSmoother().run(m, pinned.observations)
    assert not passes


def test_forward_pass_profile_equals_log_likelihood_terms(pinned):
    """The forward pass's log-likelihood is the prediction-error decomposition: -1/2 (sum NIS +
    sum log det S + m log 2 pi)."""
    m = benchmark_model(pinned, "perfect_kf")
    lin = linearise(m, np.tile(m.x0, (m.n_frames, 1)), sensitivity=False)
    fwd = kalman_forward(lin, pinned.observations)
    logdet = sum(np.linalg.slogdet(S)[1] for S in fwd.S)
    expected = -0.5 * (np.nansum(fwd.nis) + logdet + fwd.n_obs.sum() * np.log(2 * np.pi))
    assert abs(fwd.log_likelihood - expected) <= 1e-10 * abs(expected)
    assert abs(fwd.fit - 0.5 * np.nansum(fwd.nis)) == 0.0


def test_smoother_row_of_the_comparison_keeps_table_1(pinned):
    """The fourth row: not rejected, D between the uniform and the perfect material's, E error in
    the middle part no worse than the joint EKF's (seed 0; all five seeds in the slow test)."""
    from sfem_filters.benchmark.comparison import run_strategy
    rows = {s: run_strategy(pinned, s).metrics for s in ("uniform_kf", "perfect_kf", "joint_ekf", "joint_smoother")}
    sm = rows["joint_smoother"]
    assert sm["ks_H"] == 0 and rows["perfect_kf"]["ks_D"] <= sm["ks_D"] < rows["uniform_kf"]["ks_D"]
    assert sm["E_rel_error_middle"] <= rows["joint_ekf"]["E_rel_error_middle"]
    assert sm["method"] == "iterated_smoother" and sm["converged"]


@pytest.mark.parametrize("parameterisation", ["regions", "elements"])
def test_linearisation_with_and_without_modal_stiffness_derivatives(pinned, monkeypatch, parameterisation):
    """``SFEMModel.linearise`` makes the modal stiffness derivatives once when they pay
    (:func:`sfem_filters.fem.modal_stiffness.modal_stiffness_pays`): its M_t are those of the direct
    sensitivity at every frame, to round-off, and the choice follows the cost and the memory cap."""
    param = (Parameterisation.per_region(pinned.middle) if parameterisation == "regions"
             else Parameterisation.per_element(pinned.mesh.n_elements))
    m = benchmark_model(pinned, "joint_ekf", parameterisation=param)
    z = np.tile(m.x0, (m.n_frames, 1))
    z[:, : m.dim_x] += 1e-4 * np.random.default_rng(2).standard_normal((m.n_frames, m.dim_x))
    made = []
    real = model_module.ModalSystem.modal_stiffness_derivatives
    monkeypatch.setattr(model_module.ModalSystem, "modal_stiffness_derivatives",
                        lambda self, *a: made.append(1) or real(self, *a))
    fast = m.linearise(z)
    assert bool(made) == (parameterisation == "regions")      # every element's own parameter: no
    monkeypatch.setattr(modal_stiffness_module, "MODAL_STIFFNESS_BYTES", 0)
    m._modal_cache.clear()
    made.clear()
    direct = m.linearise(z)
    assert not made
    assert np.abs(fast.M - direct.M).max() <= 1e-11 * np.abs(direct.M).max()


def test_modal_stiffness_pays_by_cost_and_memory():
    """Made when building them and a pass over G per frame cost less than half the products
    they save, and they fit in the memory cap; not for as many parameters as dofs (the
    per-element map); arguments checked."""
    rng = np.random.default_rng(0)
    P, n = 60, 400
    dofs = rng.integers(0, n, (P, 6))
    few = fem.stiffness_plan(np.eye(4)[np.arange(P) % 4] @ rng.standard_normal((4, 3)), dofs)   # 3 parameters
    assert modal_stiffness_module.modal_stiffness_pays(few, 30, n)
    assert not modal_stiffness_module.modal_stiffness_pays(few, 1, 20)             # nothing to save over one frame
    many = fem.stiffness_plan(np.eye(P), dofs)                                # a parameter per direction
    assert not modal_stiffness_module.modal_stiffness_pays(many, 30, n)
    cap = 8 * (3 + 4) * n * n                                             # (k + groups) n^2 floats while made
    for limit, expected in ((cap, True), (cap - 1, False)):
        modal_stiffness_module.MODAL_STIFFNESS_BYTES, saved = limit, modal_stiffness_module.MODAL_STIFFNESS_BYTES
        try:
            assert modal_stiffness_module.modal_stiffness_pays(few, 30, n) == expected
        finally:
            modal_stiffness_module.MODAL_STIFFNESS_BYTES = saved
    with pytest.raises(ValueError, match="frames: expected an integer >= 1"):
        modal_stiffness_module.modal_stiffness_pays(few, 0, n)
    with pytest.raises(ValueError, match="n: expected an integer >= 1"):
        modal_stiffness_module.modal_stiffness_pays(few, 30, 0.5)


def test_modal_stiffness_budget_grows_with_the_memory_available(monkeypatch):
    """Unset, the budget is a quarter of the memory available and at least its floor, so a
    larger state, which needs them most, gets them where the machine holds them; set, it is the
    setting."""
    floor = modal_stiffness_module.MODAL_STIFFNESS_FLOOR
    monkeypatch.setattr(modal_stiffness_module, "MODAL_STIFFNESS_BYTES", None)
    for available, budget in ((16e9, 4e9), (1e9, floor), (None, floor)):
        monkeypatch.setattr(modal_stiffness_module, "available_memory", lambda: available)
        assert modal_stiffness_module.modal_stiffness_budget() == budget
    rng = np.random.default_rng(0)
    P, n = 60, 4000
    few = fem.stiffness_plan(np.eye(4)[np.arange(P) % 4] @ rng.standard_normal((4, 3)), rng.integers(0, n, (P, 6)))
    made = 8 * (3 + 4) * n * n                                 # 896 MB while made: above the floor
    assert made > floor
    monkeypatch.setattr(modal_stiffness_module, "available_memory", lambda: 4 * made)
    assert modal_stiffness_module.modal_stiffness_pays(few, 30, n)
    monkeypatch.setattr(modal_stiffness_module, "available_memory", lambda: 4 * made - 8)
    assert not modal_stiffness_module.modal_stiffness_pays(few, 30, n)
    monkeypatch.setattr(modal_stiffness_module, "MODAL_STIFFNESS_BYTES", made)
    assert modal_stiffness_module.modal_stiffness_pays(few, 30, n)
