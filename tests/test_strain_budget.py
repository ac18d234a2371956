"""The strain-budget claim's resampled cases (validation/strain_budget.py): a finer or coarser grid, the same case."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import given, settings, strategies as st

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sfem_filters.imaging import phase_to_displacement, read_dense_sim  # noqa: E402
from validation.strain_budget import (  # noqa: E402
    _zoom_mask, fourier_operator, matrix_for_pixels, resampled_pixels, write_resampled_case)

N, FOV_MM, KE, N_ACQ, FRAMES = 48, 96.0, 0.1, 24, 3


def _annulus(n=N, inner=7.0, outer=14.0):
    yy, xx = np.mgrid[0:n, 0:n]
    d = np.hypot(xx - (n - 1) / 2, yy - (n - 1) / 2)
    return (d >= inner) & (d <= outer)


def _write_case(folder: Path, shift_mm=(0.0, 0.0), truth=0.1) -> Path:
    """A DENSE-Sim folder of an annulus translated by ``shift_mm`` (x, y) in every frame."""
    folder.mkdir(parents=True, exist_ok=True)
    mask = _annulus()
    ones = np.ones((FRAMES, N, N))
    for name, d in (("phase_x", shift_mm[0]), ("phase_y", shift_mm[1])):
        np.save(folder / f"{name}.npy", np.angle(np.exp(2j * np.pi * KE * d) * ones).astype(np.float32))
    np.save(folder / "magnitude.npy", np.where(mask, 1.0, 0.05)[None].repeat(FRAMES, 0).astype(np.float32))
    np.save(folder / "LV_mask_time_lowres.npy", mask[None].repeat(FRAMES + 1, 0))
    gt = np.where(mask, truth, np.nan)[None].repeat(FRAMES, 0).astype(np.float32)
    np.save(folder / "GT_Ecc.npy", -gt)
    np.save(folder / "GT_Err.npy", gt)
    cfg = {"sim_params": {"FOV": [FOV_MM, FOV_MM, 8], "N_im": N, "N_im_pre_spiral": N_ACQ, "ke": KE,
                          "tt": [0.0] + [20.0 + 15.0 * f for f in range(FRAMES)], "Nt": FRAMES}}
    with open(folder / "config.yaml", "w") as fh:
        yaml.safe_dump(cfg, fh)
    return folder


def test_zoom_one_reproduces_the_case(tmp_path):
    src = _write_case(tmp_path / "src", (1.3, -0.4))
    write_resampled_case(src, tmp_path / "dst", 1.0)
    a, b = read_dense_sim(src), read_dense_sim(tmp_path / "dst")
    assert np.array_equal(a.masks, b.masks)
    assert np.allclose(a.phases, b.phases, atol=1e-5)
    assert np.allclose(a.truth_err, b.truth_err, equal_nan=True)
    assert b.pixel_size_m == pytest.approx(a.pixel_size_m) and b.resolution_px == pytest.approx(a.resolution_px)
    assert np.array_equal(a.frame_times_s, b.frame_times_s)


@settings(max_examples=8, deadline=None)
@given(zoom=st.floats(0.65, 1.6), dx=st.floats(-2.0, 2.0), dy=st.floats(-2.0, 2.0),
       method=st.sampled_from(["linear", "fourier"]))
def test_a_finer_or_coarser_grid_keeps_the_anatomy_the_motion_and_the_acquisition(tmp_path_factory, zoom, dx, dy,
                                                                                   method):
    tmp = tmp_path_factory.mktemp("zoom")
    src = _write_case(tmp / "src", (dx, dy))
    info = write_resampled_case(src, tmp / "dst", zoom, method=method)
    a, b = read_dense_sim(src), read_dense_sim(tmp / "dst")
    n_new = info["n_im"]
    assert n_new == round(N * zoom)
    # the field of view and the acquired pixel stay; the pixel shrinks by the new matrix over the old
    assert b.pixel_size_m * n_new == pytest.approx(a.pixel_size_m * N)
    assert b.pixel_size_m == pytest.approx(a.pixel_size_m * N / n_new)
    assert b.resolution_px == pytest.approx(n_new / N_ACQ)
    # the myocardium's area in mm^2 is kept (to the quantisation of its two borders)
    area = lambda c: c.reference_mask.sum() * c.pixel_size_mm ** 2     # noqa: E731
    assert area(b) == pytest.approx(area(a), rel=0.12)
    assert info["reference_pixels"] == int(b.reference_mask.sum())
    # the motion: a translation of (dx, dy) mm is (dx, dy) mm at every reference pixel
    tracks = phase_to_displacement(b)
    disp_mm = tracks.displacement * b.pixel_size_mm
    ok = np.isfinite(disp_mm).all(axis=-1)
    assert ok.mean() > 0.95
    assert np.allclose(disp_mm[ok], [dx, dy], atol=1e-3)
    # the truth where it is known, and only on the reference myocardium
    assert np.allclose(b.truth_err[:, b.reference_mask], 0.1, atol=1e-6)
    assert np.isnan(b.truth_err[:, ~b.reference_mask]).all()


def test_frames_keep_the_first_ones_and_their_times(tmp_path):
    src = _write_case(tmp_path / "src")
    write_resampled_case(src, tmp_path / "dst", 1.0, frames=2)
    a, b = read_dense_sim(src), read_dense_sim(tmp_path / "dst")
    assert b.n_frames == 2 and b.masks.shape[0] == 3
    assert np.array_equal(b.frame_times_s, a.frame_times_s[:2])


def test_matrix_for_pixels_is_the_smallest_matrix_that_reaches_the_target():
    mask = _annulus()
    size, own = mask.shape[0], int(mask.sum())
    for target in (own // 2, own, own + 1, int(own * 1.7)):
        n, zoom, pixels, tried = matrix_for_pixels(mask, target)
        assert zoom == n / size and pixels == resampled_pixels(mask, zoom) >= target
        # every smaller matrix from the mask's own size upwards falls short, and each was tried
        assert all(resampled_pixels(mask, m / size) < target for m in range(size, n))
        assert [t[0] for t in tried] == list(range(size, n + 1))
        # the zoom makes exactly an n x n image: the matrix the resampled case's config states
        assert _zoom_mask(mask, zoom).shape == (n, n)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="zoom"):
        write_resampled_case(".", ".", 0.0)
    with pytest.raises(ValueError, match="reference_mask"):
        matrix_for_pixels(np.zeros((4, 4), bool), 10)
    with pytest.raises(ValueError, match="reference_mask"):
        matrix_for_pixels(np.ones((4, 5), bool), 10)
    with pytest.raises(ValueError, match="target"):
        matrix_for_pixels(_annulus(), 0)


@settings(max_examples=25, deadline=None)
@given(n_old=st.integers(8, 70), n_new=st.integers(8, 70), phase=st.floats(-3.0, 3.0), data=st.data())
def test_the_fourier_operator_samples_a_band_limited_image_on_the_new_grid(n_old, n_new, phase, data):
    """Any frequency both grids hold is sampled exactly at the new pixel centres (edges aligned); the
    same grid gives the identity."""
    R = fourier_operator(n_old, n_new)
    assert R.shape == (n_new, n_old)
    k = data.draw(st.integers(0, (min(n_old, n_new) - 1) // 2), label="k")
    x_old = np.arange(n_old)
    x_new = (np.arange(n_new) + 0.5) * n_old / n_new - 0.5
    f = lambda x: np.cos(2 * np.pi * k * x / n_old + phase)      # noqa: E731
    assert np.allclose(R @ f(x_old), f(x_new), atol=1e-10)
    assert np.allclose(fourier_operator(n_old, n_old), np.eye(n_old), atol=1e-12)


def test_the_fourier_resampling_keeps_the_case_at_zoom_one_and_refuses_an_unknown_method(tmp_path):
    src = _write_case(tmp_path / "src", (0.7, 0.2))
    write_resampled_case(src, tmp_path / "dst", 1.0, method="fourier")
    a, b = read_dense_sim(src), read_dense_sim(tmp_path / "dst")
    assert np.array_equal(a.masks, b.masks)
    assert np.allclose(np.angle(np.exp(1j * (a.phases - b.phases))), 0.0, atol=1e-5)
    with pytest.raises(ValueError, match="method: expected 'linear' or 'fourier'"):
        write_resampled_case(src, tmp_path / "bad", 0.8, method="cubic")


def test_a_resampled_case_leaves_the_simulators_output_grids_and_a_case_on_one_is_refused(tmp_path):
    src = _write_case(tmp_path / "src")
    cfg = yaml.safe_load((src / "config.yaml").read_text())
    cfg["sim_params"]["output_dim"] = {"sizes": [N, 20], "FOVs": [FOV_MM, 40.0]}
    (src / "config.yaml").write_text(yaml.safe_dump(cfg))
    info = write_resampled_case(src, tmp_path / "dst", 0.75)
    new = yaml.safe_load((tmp_path / "dst" / "config.yaml").read_text())["sim_params"]
    assert new["N_im"] == info["n_im"] and "output_dim" not in new      # N_im over FOV, whatever output_dim said
    # a case written on another of output_dim's grids: its pixel is not FOV / N_im, so the resampling refuses it
    cfg["sim_params"]["N_im"] = 2 * N
    cfg["sim_params"]["output_dim"] = {"sizes": [2 * N, N], "FOVs": [FOV_MM, FOV_MM / 2]}
    (src / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ValueError, match=r"src: expected a case on its config's N_im grid"):
        write_resampled_case(src, tmp_path / "dst2", 0.75)
