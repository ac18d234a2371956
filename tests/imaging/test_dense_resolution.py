"""The acquired resolution of DENSE images: from DENSE-Sim's config, a DICOM's AcquisitionMatrix or the user,
its point spread, its cross-check by the magnitude's edge spread, and the static background's signal.

Ground truth from data we did not write: the DENSE-Sim cases' config (their simulator's acquisition matrix)
against their magnitude images' edge spread.
"""
import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st
from pydicom.dataset import Dataset

from sfem_filters.cardiac.strain_route import StrainRouteSettings
from sfem_filters.imaging.dense import (DEFAULT_RESOLUTION_PX, FWHM_PER_SD, add_complex_noise, dicom_resolution_px,
                                        edge_spread_resolution, make_dense_case, psf_samples, psf_sigma_px,
                                        read_dense_sim)
from test_dense import DENSE_SIM, needs_data, write_case_folder


def test_the_config_gives_the_acquired_resolution_and_noise_keeps_it(tmp_path):
    folder = write_case_folder(tmp_path / "c")
    assert read_dense_sim(folder).resolution_px == DEFAULT_RESOLUTION_PX          # nothing said: 1
    cfg = yaml.safe_load((folder / "config.yaml").read_text())
    cfg["sim_params"]["N_im_pre_spiral"] = 16                                    # N_im 24
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    case = read_dense_sim(folder)
    assert case.resolution_px == pytest.approx(1.5)
    assert add_complex_noise(case, 10.0, 0).resolution_px == pytest.approx(1.5)
    cfg["sim_params"]["N_im_pre_spiral"] = 48                                    # coarser image than its data
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ValueError, match="config.yaml N_im / N_im_pre_spiral: expected the acquired resolution"):
        read_dense_sim(folder)


@pytest.mark.parametrize("bad", [0.5, 0.0, -2.0, float("nan"), float("inf"), "wide", None])
def test_a_bad_resolution_is_a_clear_error_naming_it(bad):
    ring = np.zeros((8, 8), bool)
    ring[2:6, 2:6] = True
    ring[3:5, 3:5] = False
    with pytest.raises(ValueError, match="resolution_px: expected the acquired resolution in reconstructed pixels"):
        make_dense_case(np.zeros((2, 1, 8, 8)), np.ones((1, 8, 8)), np.stack([ring, ring]), 1.75, 0.1, [0.02],
                        resolution_px=bad)
    with pytest.raises(ValueError, match="resolution_px: expected the acquired resolution in reconstructed pixels"):
        StrainRouteSettings(resolution_px=bad)
    with pytest.raises(ValueError, match="resolution_px: expected"):
        psf_sigma_px(bad)


@pytest.mark.parametrize("matrix, rows, cols, expected", [
    ((60, 0, 0, 60), 128, 128, 128 / 60),          # frequency along rows, zero-filled to 128
    ((0, 96, 80, 0), 160, 192, 2.0),               # frequency along columns: 96 columns, 80 rows acquired
    ((256, 0, 0, 256), 256, 256, 1.0),
    ((256, 0, 0, 256), 128, 128, 1.0),             # a reconstruction coarser than the acquisition: no blur beyond it
    (None, 128, 128, DEFAULT_RESOLUTION_PX)])
def test_dicom_resolution_is_the_image_matrix_over_the_acquisition_matrix(matrix, rows, cols, expected):
    ds = Dataset()
    ds.Rows, ds.Columns = rows, cols
    if matrix is not None:
        ds.AcquisitionMatrix = list(matrix)
    assert dicom_resolution_px(ds) == pytest.approx(expected)


@settings(max_examples=30, deadline=None)
@given(st.floats(1.0, 4.0))
def test_the_psf_has_the_acquired_fwhm_beyond_the_pixels_own(w):
    sd = psf_sigma_px(w)
    # the Gaussian of the pixel's own FWHM (1) convolved with the PSF has the acquired FWHM
    assert np.hypot(1.0, FWHM_PER_SD * sd) == pytest.approx(w, rel=1e-9)
    off, wt = psf_samples(w)
    assert wt.sum() == pytest.approx(1.0) and np.all(wt >= 0)
    assert np.allclose(wt @ off, 0.0, atol=1e-12)                       # symmetric about the centre
    if sd > 0.3:                                                        # resolved by the third-of-a-pixel lattice
        assert np.sqrt(wt @ off[:, 0] ** 2) == pytest.approx(sd, rel=0.05)
    assert np.array_equal(psf_samples(1.0)[0], np.zeros((1, 2)))         # no blur: the point


@needs_data
@pytest.mark.parametrize("name", ["invivo_subject_1", "phantom_subject_1"])
def test_the_magnitudes_edge_spread_agrees_with_the_configs_acquisition(name):
    case = read_dense_sim(DENSE_SIM / name)
    assert case.resolution_px == pytest.approx(128 / 60)
    est = edge_spread_resolution(case, frames=range(0, case.n_frames, 4))
    assert abs(est["resolution_px"] - case.resolution_px) < 0.25 * case.resolution_px
    assert est["resolution_px"] > 1.5                                     # the images are blurred beyond the pixel
