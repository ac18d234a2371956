"""The pinned benchmark and the paper's three-way comparison (section 3.1, Table 1)."""
import json
import subprocess
import sys

import numpy as np
import pytest

from sfem_filters.benchmark.comparison import run_comparison
from sfem_filters.benchmark.pinned import (
    FRAME_INTERVAL,
    MM,
    MMHG,
    benchmark_model,
    pinned_benchmark,
    pressure_mmhg,
)
from sfem_filters.fem.statespace import continuous_matrices, discretize_zoh


def test_benchmark_setup_follows_the_spec():
    b = pinned_benchmark(0)
    assert b.mesh.n_nodes == 35 and b.mesh.n_elements == 48
    assert b.observation_operator.shape == (26, 70)
    np.testing.assert_array_equal(b.observed_nodes, [7, 13, 14, 20, 21, 27, 28, 29, 30, 31, 32, 33, 34])
    assert b.middle.sum() == 16                     # two of six columns of cells, 8 triangles each
    np.testing.assert_allclose(b.true_material.E[b.middle], 105e3)
    np.testing.assert_allclose(b.true_material.nu[~b.middle], 0.40)
    P = pressure_mmhg()
    assert P[0] == 0 and P[8] == pytest.approx(58.2)
    # total top load = -P * width (N per metre depth), in y
    np.testing.assert_allclose(b.loads[:, 1::2].sum(axis=1), -P * MMHG * 60 * MM, rtol=1e-12)
    np.testing.assert_allclose(b.loads[:, 0::2].sum(axis=1), 0.0, atol=1e-9)
    # noise is exactly the pinned draw
    noise = b.observations - (b.observation_operator @ b.U.T).T
    np.testing.assert_allclose(noise, np.random.default_rng(0).standard_normal((16, 26)) * 0.1 * MM, atol=1e-15)
    # frame 1 at rest; the top moves down under pressure
    assert np.all(b.U[0] == 0) and np.all(b.V[0] == 0)
    top = b.mesh.nodes_where(lambda x, y: y > 39.9 * MM)
    assert np.all(b.U[8, 2 * top + 1] < 0)


def test_ground_truth_equals_the_literal_discretisation():
    """Truth from the modal route equals x_{k+1} = A x_k + B w_{k+1} with A, B from Eqs. (14)-(16)."""
    b = pinned_benchmark(0)
    m = benchmark_model(b, "perfect_kf")
    M = m.M
    K = m.system().Phi  # noqa: F841 (only to build the cache)
    from sfem_filters.fem import stiffness_matrix
    K = m.dofmap.restrict_matrix(stiffness_matrix(b.mesh, b.true_material.E, b.true_material.nu)).toarray()
    A, B = discretize_zoh(*continuous_matrices(M, K, 10 * M + 1e-3 * K), FRAME_INTERVAL)
    x = np.zeros(2 * M.shape[0])
    w = m.dofmap.restrict(b.loads)
    for t in range(1, 16):
        x = A @ x + B @ w[t]
        np.testing.assert_allclose(m.displacements(x), b.U[t], atol=1e-9 * np.abs(b.U).max())


def test_noise_level_and_refinement_options():
    b = pinned_benchmark(3, refine=2, noise_mm=0.2)
    assert b.mesh.n_nodes == 13 * 9 and b.observation_operator.shape[0] == 2 * (13 + 2 * 7)
    noise = b.observations - (b.observation_operator @ b.U.T).T
    assert noise.std() == pytest.approx(0.2 * MM, rel=0.1)
    with pytest.raises(ValueError, match="noise_mm: expected a positive"):
        pinned_benchmark(0, noise_mm=0)
    with pytest.raises(ValueError, match="refine: expected an integer >= 1"):
        pinned_benchmark(0, refine=0)
    with pytest.raises(ValueError, match="strategy: expected one of"):
        benchmark_model(b, "ukf")


def _check_table1(metrics):
    """The paper's qualitative Table 1 and the issue's ordering."""
    u, p, e = metrics["uniform_kf"], metrics["perfect_kf"], metrics["joint_ekf"]
    assert u["ks_H"] == 1 and p["ks_H"] == 0 and e["ks_H"] == 0
    assert e["ks_D"] < u["ks_D"]
    assert p["ks_D"] <= e["ks_D"] + 2 / 35 + 1e-12
    assert e["rmse_displacement_mm"] < u["rmse_displacement_mm"]
    assert e["rmse_eyy"] < u["rmse_eyy"]


@pytest.fixture(scope="module")
def cli_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("compare")
    proc = subprocess.run([sys.executable, "-m", "sfem_filters.cli", "compare", "--seed", "0", "--no-progress",
                           "--json", str(out / "c.json"), "--figures", str(out / "fig")],
                          capture_output=True, text=True, timeout=600)
    return proc, out


def test_compare_cli_reproduces_table1_seed0(cli_run):
    proc, out = cli_run
    assert proc.returncode == 0, proc.stderr
    data = json.loads((out / "c.json").read_text())
    assert data["seed"] == 0 and data["refine"] == 1 and data["frame"] == 9
    keys = {"ks_D", "ks_p_exact", "ks_p_asymptotic", "ks_H", "rmse_displacement_mm", "rmse_eyy", "seconds"}
    for s in ("uniform_kf", "perfect_kf", "joint_ekf"):
        assert keys <= set(data["strategies"][s])
    assert {"loops", "E_rel_error_middle", "E_rel_error_outside", "nu_rel_error_middle",
            "nu_rel_error_outside"} <= set(data["strategies"]["joint_ekf"])
    _check_table1(data["strategies"])
    # seed 0: better than the uniform assumption inside the stiff part (its error there is 0.286);
    # not every seed is (the reference range reaches 0.32, our seed 4 gives 0.316)
    assert data["strategies"]["joint_ekf"]["E_rel_error_middle"] < 0.286
    for name in ("displacement_maps.png", "eyy_frame9.png", "eyy_cdfs_frame9.png", "material_maps.png",
                 "convergence.png"):
        assert (out / "fig" / name).stat().st_size > 10_000
    assert "joint EKF" in proc.stdout and "paper (Table 1)" in proc.stdout


def test_compare_cli_user_errors_have_no_traceback():
    proc = subprocess.run([sys.executable, "-m", "sfem_filters.cli", "compare", "--noise-mm", "-1"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and "expected a positive number" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_table1_all_seeds(seed):
    """Seeds 0-4: qualitative Table 1 and the neighbourhood the issue gives for the joint EKF."""
    comp = run_comparison(seed)
    m = {k: r.metrics for k, r in comp.runs.items()}
    _check_table1(m)
    e = m["joint_ekf"]
    assert 0.06 <= e["rmse_displacement_mm"] <= 0.12
    assert 0.10 <= e["E_rel_error_middle"] <= 0.35 and e["E_rel_error_outside"] <= 0.15
    assert 2 <= e["loops"] <= 50
