"""ParaView export: the files read back with meshio, every field present with the in-memory values."""
import numpy as np
import pytest

from sfem_filters.benchmark.comparison import run_comparison
from sfem_filters.cardiac import EstimatorSettings, LoopSettings, annulus_sequence, closing_the_loop
from sfem_filters.export import export_comparison, export_dense, read_series, write_series


def test_write_series_round_trip_and_bad_input(tmp_path):
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 1e-2, (5, 2))
    cells = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4]])
    disp = rng.standard_normal((3, 5, 2))
    E = rng.uniform(1e3, 1e4, 3)
    pvd = write_series(tmp_path, "m", pts, cells, [0.0, 0.1, 0.2], {"u": disp, "c": np.arange(5.0)}, {"E": E})
    frames = read_series(pvd)
    assert [t for t, _ in frames] == [0.0, 0.1, 0.2]
    for t, (_, mesh) in enumerate(frames):
        np.testing.assert_allclose(mesh.points[:, :2], pts)
        np.testing.assert_allclose(mesh.point_data["u"][:, :2], disp[t])
        assert np.all(mesh.point_data["u"][:, 2] == 0)
        np.testing.assert_allclose(mesh.point_data["c"], np.arange(5.0))
        np.testing.assert_allclose(mesh.cell_data["E"][0], E)
    with pytest.raises(ValueError, match="name"):
        write_series(tmp_path, "bad name", pts, cells, [0.0])
    with pytest.raises(ValueError, match="u: expected"):
        write_series(tmp_path, "m2", pts, cells, [0.0], {"u": np.zeros((4, 2))})


def test_export_dense_fields_match_the_result(tmp_path):
    out = closing_the_loop(annulus_sequence("active_polar", n_frames=6, seed=0),
                           estimator=EstimatorSettings(max_iterations=2), loop=LoopSettings(effects="active_polar"))
    tissue, points = export_dense(out, tmp_path)
    ext, setup = out.extended, out.setup
    series = read_series(tissue)
    assert len(series) == setup.seq.n_frames
    U = ext.model.displacements(ext.result.states)
    for t, (time, mesh) in enumerate(series):
        assert np.isclose(time, t * setup.frame_interval)
        assert set(mesh.point_data) >= {"displacement_m", "velocity_m_s", "strain_polar", "strain_polar_sd"}
        assert set(mesh.cell_data) >= {"E_Pa", "nu", "E_sd_log", "nu_sd", "region"}
        np.testing.assert_allclose(mesh.point_data["displacement_m"][:, :2], U[t].reshape(-1, 2))
        np.testing.assert_allclose(mesh.point_data["strain_polar"][setup.node_of_point],
                                   np.asarray(ext.metrics["strain_polar"])[t])
    mat = ext.model.material_of_theta(ext.result.theta)
    np.testing.assert_allclose(series[0][1].cell_data["E_Pa"][0], mat.E)
    pc = ext.metrics["prior_conflict"]
    for k in ("E", "nu"):
        want = np.array([np.nan if v is None else v for v in pc[f"{k}_z"]], float)
        np.testing.assert_allclose(series[0][1].cell_data[f"prior_conflict_z_{k}"][0], want, equal_nan=True)
    cloud = read_series(points)
    last = cloud[-1][1]
    assert last.points.shape[0] == setup.seq.n_points
    np.testing.assert_array_equal(np.flatnonzero(last.point_data["observed"]), np.sort(setup.observed))
    np.testing.assert_allclose(last.point_data["residual_m"][:, :2],
                               (setup.seq.displacement[-1] - ext.U[-1]) * setup.spacing)


@pytest.mark.slow
def test_export_comparison_has_every_strategy(tmp_path):
    comp = run_comparison(0)
    paths = export_comparison(comp, tmp_path)
    assert len(paths) == 1 + len(comp.runs)
    truth = read_series(paths[0])
    np.testing.assert_allclose(truth[3][1].point_data["displacement_m"][:, :2], comp.bench.U[3].reshape(-1, 2))
    for path, (name, r) in zip(paths[1:], comp.runs.items()):
        s = read_series(path)
        np.testing.assert_allclose(s[-1][1].point_data["strain"], r.strain[-1])
        np.testing.assert_allclose(s[0][1].cell_data["E_Pa"][0], r.model.material_of_theta(r.result.theta).E)
        sd = getattr(r.result, "output_sd", {}).get("strain")
        if name == "joint_smoother":
            assert sd is not None
        if sd is not None:
            np.testing.assert_allclose(s[4][1].point_data["strain_sd"], np.asarray(sd)[4].reshape(-1, 3))
            assert np.all(s[4][1].point_data["strain_sd"] >= 0) and np.median(s[4][1].point_data["strain_sd"]) > 0
        else:
            assert "strain_sd" not in s[4][1].point_data
