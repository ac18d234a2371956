"""Faults, round-off and divergence: nothing silent, nothing lost (issue 6, first part)."""
import os
import signal
import subprocess
import sys
import textwrap
import time
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import sfem_filters.filtering.cyclic as cyclic_module
from helpers import count_calls
from sfem_filters.benchmark.pinned import benchmark_model, pinned_benchmark
from sfem_filters.filtering import (
    ENGINES,
    FilterDivergence,
    Safeguards,
    cyclic_estimate,
    filter_loop,
    load_checkpoint,
    nearest_psd,
)

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

RUN = textwrap.dedent("""
    import sys, warnings
    warnings.simplefilter("ignore")
    from sfem_filters.filtering import cyclic_estimate
    from sfem_filters.benchmark.pinned import benchmark_model, pinned_benchmark
    b = pinned_benchmark(0)
    cyclic_estimate(benchmark_model(b, "joint_ekf"), b.observations, max_loops=int(sys.argv[2]), tol=1e-12,
                    checkpoint=sys.argv[1])
""")


def test_killed_run_resumes_to_the_uninterrupted_result(tmp_path, monkeypatch):
    """SIGKILL during a loop; resuming from the last checkpoint runs only the loops left and ends bit-identical."""
    ckpt = str(tmp_path / "run.npz")
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen([sys.executable, "-c", RUN, ckpt, "8"], env=env)
    deadline = time.time() + 300
    while time.time() < deadline:
        if os.path.exists(ckpt):
            try:
                if int(load_checkpoint(ckpt)["loops_done"]) >= 2:
                    break
            except ValueError:
                pass           # caught mid-write by the atomic replace: look again
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = int(load_checkpoint(ckpt)["loops_done"])
    assert 2 <= done < 8, "the run was not interrupted mid-way"
    b = pinned_benchmark(0)
    loops = count_calls(monkeypatch, cyclic_module, "filter_loop")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        resumed = cyclic_estimate(benchmark_model(b, "joint_ekf"), b.observations, max_loops=8, tol=1e-12,
                                  checkpoint=ckpt)
        assert len(loops) == 8 - done               # it went on from the checkpoint, not from the start
        full = cyclic_estimate(benchmark_model(b, "joint_ekf"), b.observations, max_loops=8, tol=1e-12)
    np.testing.assert_array_equal(resumed.theta, full.theta)
    np.testing.assert_array_equal(resumed.P_theta, full.P_theta)
    np.testing.assert_array_equal(resumed.states, full.states)


def test_same_inputs_same_outputs_bit_for_bit():
    b = pinned_benchmark(2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r1 = cyclic_estimate(benchmark_model(b, "joint_ekf"), b.observations, max_loops=2)
        r2 = cyclic_estimate(benchmark_model(pinned_benchmark(2), "joint_ekf"), pinned_benchmark(2).observations,
                             max_loops=2)
    np.testing.assert_array_equal(r1.theta, r2.theta)
    np.testing.assert_array_equal(r1.history.as_arrays()["x"], r2.history.as_arrays()["x"])


def test_nearest_psd_is_the_eigenvalue_clip():
    rng = np.random.default_rng(0)
    A = rng.standard_normal((6, 6))
    P = A @ A.T
    P[0, 0] -= 40.0                                   # indefinite
    Q = nearest_psd(P)
    assert np.linalg.eigvalsh(Q).min() >= -1e-12
    np.testing.assert_allclose(Q, Q.T)
    # no PSD matrix is closer (checked against random PSD candidates)
    for _ in range(50):
        B = rng.standard_normal((6, 6))
        C = Q + 0.05 * B @ B.T
        assert np.linalg.norm(P - Q) <= np.linalg.norm(P - C) + 1e-12


def test_indefinite_covariance_is_repaired_and_logged():
    b = pinned_benchmark(0)
    model = benchmark_model(b, "perfect_kf")
    eng = ENGINES["structured"](model)
    P = model.P0.copy()
    P[3, 3] = -P[3, 3]                                 # corrupt the initial covariance
    eng.reset(model.x0, P)
    guard = Safeguards()
    with pytest.warns(RuntimeWarning, match="covariance repaired"):
        filter_loop(eng, model, b.observations, safeguards=guard)
    assert guard.repairs and np.linalg.eigvalsh(eng.P).min() > 0
    eng.reset(model.x0, P)
    with pytest.raises(FloatingPointError, match="P lost positive definiteness"):
        filter_loop(eng, model, b.observations, safeguards=Safeguards(covariance_repair="none"))
    with pytest.raises(ValueError, match="covariance_repair: expected 'higham' or 'none'"):
        Safeguards(covariance_repair="clip")


def test_divergence_is_reported_and_can_stop_the_run():
    """Data from another world (offset by 5 mm): NIS far outside its band -> warning / stop."""
    b = pinned_benchmark(0)
    model = benchmark_model(b, "perfect_kf")
    y = b.observations + 5e-3
    with pytest.warns(RuntimeWarning, match=r"filter inconsistent: the innovations' normalised squares \(NIS\) "
                                            r"above their 99.9% chi-square bound"):
        cyclic_estimate(model, y)
    with pytest.raises(FilterDivergence, match="for 4 frames in a row"):
        cyclic_estimate(model, y, safeguards=Safeguards(stop_on_divergence=True))
    with warnings.catch_warnings():
        warnings.simplefilter("error")                 # consistent data: no warning at all
        cyclic_estimate(model, b.observations)


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), noise=st.floats(1e-6, 1e-4), missing=st.floats(0.0, 0.6),
       repair=st.sampled_from(["higham", "none"]), engine=st.sampled_from(["structured", "ud"]))
def test_random_missing_data_keeps_P_spd_and_material_admissible(seed, noise, missing, repair, engine):
    """Random meshes, materials, noise levels and missing-data masks (single values and whole
    frames), 16 frames x 3 loops, Joseph-form or U-D engine: P stays symmetric positive definite (so the 'none' setting
    never has to stop), the material admissible, and nothing is NaN."""
    from helpers import random_block_mesh, small_model
    rng = np.random.default_rng(seed)
    model = small_model(rng, mesh=random_block_mesh(rng, n_interior=int(rng.integers(2, 7))), noise=noise,
                        n_frames=16)
    from helpers import simulate
    y = simulate(model, rng, noise)                                 # data the model can explain
    y[rng.random(y.shape) < missing] = np.nan
    y[rng.integers(1, 16)] = np.nan                                  # one frame with nothing observed
    guard = Safeguards(covariance_repair=repair)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = cyclic_estimate(model, y, max_loops=3, tol=1e-12, safeguards=guard, engine=engine)
    h = res.history.as_arrays()
    assert np.all(np.isfinite(h["x"])) and np.all(np.isfinite(h["P_diag"]))
    assert np.all(h["P_diag"] > 0)
    assert not guard.repairs
    C = res.P_theta / np.sqrt(np.outer(np.diag(res.P_theta), np.diag(res.P_theta)))
    assert np.linalg.eigvalsh(0.5 * (C + C.T)).min() > 0
    mat = model.material_of_theta(res.theta)
    assert np.all(mat.E > 0) and np.all((mat.nu > 0) & (mat.nu < 0.5))
    empty = np.flatnonzero(np.all(np.isnan(y), axis=1))
    assert np.all(h["n_obs"][np.isin(h["frame"], empty)] == 0)
