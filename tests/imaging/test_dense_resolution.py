"""The acquired resolution of DENSE images: from DENSE-Sim's config, a DICOM's AcquisitionMatrix or the user,
its point spread, its cross-check by the magnitude's edge spread, and the static background's signal.

Ground truth from data we did not write: the DENSE-Sim cases' config (their simulator's acquisition matrix)
against their magnitude images' edge spread.
"""
import warnings

import numpy as np
import pytest
import yaml
from scipy import ndimage
from hypothesis import given, settings
from hypothesis import strategies as st
from pydicom.dataset import Dataset

from sfem_filters.cardiac.strain_route import StrainRouteSettings
from sfem_filters.imaging.dense import (DEFAULT_RESOLUTION_PX, FWHM_PER_SD, add_complex_noise, background_signal,
                                        dicom_resolution_px, edge_spread_resolution, make_dense_case, psf_samples,
                                        psf_sigma_px, read_dense_sim)
from sfem_filters.imaging.dense_io import dense_sim_grid
from test_dense import DENSE_SIM, needs_data, write_case_folder


def test_the_config_gives_the_acquired_resolution_and_noise_keeps_it(tmp_path):
    folder = write_case_folder(tmp_path / "c")
    cfg = yaml.safe_load((folder / "config.yaml").read_text())
    del cfg["sim_params"]["N_im_pre_spiral"]
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.warns(UserWarning, match="no sim_params.N_im_pre_spiral"):
        assert read_dense_sim(folder).resolution_px == DEFAULT_RESOLUTION_PX      # nothing said: 1, a warning
    cfg = yaml.safe_load((folder / "config.yaml").read_text())
    cfg["sim_params"]["N_im_pre_spiral"] = 16                                    # N_im 24
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    case = read_dense_sim(folder)
    assert case.resolution_px == pytest.approx(1.5)
    assert add_complex_noise(case, 10.0, 0).resolution_px == pytest.approx(1.5)
    cfg["sim_params"]["N_im_pre_spiral"] = 48                                    # coarser image than its data
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.warns(UserWarning, match="config.yaml N_im / N_im_pre_spiral: the acquired pixel .* is finer"):
        assert read_dense_sim(folder).resolution_px == DEFAULT_RESOLUTION_PX


def test_images_on_another_output_grid_take_that_grids_pixel_and_keep_the_acquired_one(tmp_path):
    # DENSE-Sim's config lists the grids a case may be written on (output_dim); a case on one that is not
    # N_im must not be read with FOV / N_im: every displacement in pixels would be off by the ratio.
    folder = write_case_folder(tmp_path / "c", n=24)                 # images 24 x 24
    cfg = yaml.safe_load((folder / "config.yaml").read_text())
    cfg["sim_params"].update({"FOV": [56.0, 56.0, 8], "N_im": 32, "N_im_pre_spiral": 16,
                              "output_dim": {"sizes": [32, 24], "FOVs": [[56.0, 56.0, 8], [48.0, 48.0, 8]]}})
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    case = read_dense_sim(folder)
    assert case.pixel_size_mm == pytest.approx(48.0 / 24)                    # the output grid's FOV over its size
    assert case.resolution_px == pytest.approx((56.0 / 16) / (48.0 / 24))     # the acquired 3.5 mm in 2 mm pixels
    cfg["sim_params"]["output_dim"]["sizes"] = [32, 90]                      # the images' size listed nowhere:
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))                 # smaller than N_im, a crop of it
    with pytest.warns(UserWarning, match=r"the images are 24 x 24 pixels, but N_im is 32 .* read as a crop"):
        assert read_dense_sim(folder).pixel_size_mm == pytest.approx(56.0 / 32)
    cfg["sim_params"].update({"N_im": 16, "FOV": [28.0, 28.0, 8], "N_im_pre_spiral": 8})   # larger than N_im
    del cfg["sim_params"]["output_dim"]
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    with pytest.raises(ValueError, match=r"config.yaml N_im: the images are 24 x 24 pixels, but N_im is 16 and "
                                         r"output_dim lists sizes \[\]"):
        read_dense_sim(folder)


SIM = {"FOV": [224, 224, 8], "N_im": 128, "N_im_pre_spiral": 60}


@pytest.mark.parametrize("output_dim, match", [
    ({"sizes": [128, 90], "FOVs": [[224, 224, 8]]}, r"output_dim: expected one FOV per size, got 2 sizes and 1 FOVs"),
    ({"sizes": 90, "FOVs": [[200, 200, 8]]}, r"output_dim: expected lists of sizes and FOVs"),
    ([128, 90], r"output_dim: expected a mapping with sizes and FOVs"),
    ({"sizes": [128, 90], "FOVs": [224, [200, 190, 8]]}, r"output_dim FOVs\[1\]: expected a square field of view"),
    ({"sizes": [128, "ninety"], "FOVs": [224, 200]}, r"output_dim sizes\[1\]"),
])
def test_a_malformed_output_dim_is_a_clear_error_naming_it(output_dim, match):
    with pytest.raises(ValueError, match=match):
        dense_sim_grid({**SIM, "output_dim": output_dim}, (90, 90))


def test_the_config_grid_edge_cases():
    # one number for a square FOV, as for the output grids
    assert dense_sim_grid({**SIM, "output_dim": {"sizes": [128, 90], "FOVs": [224, 200]}}, (90, 90))[0] == \
        pytest.approx(200 / 90)
    with pytest.raises(ValueError, match=r"config.yaml: expected the key sim_params.FOV"):
        dense_sim_grid({"N_im": 128}, (128, 128))
    with pytest.raises(ValueError, match=r"the images are 130 x 128 pixels, but N_im is 128"):
        dense_sim_grid(SIM, (130, 128))
    with pytest.warns(UserWarning, match=r"read as a crop of the N_im grid, pixel FOV / N_im = 1.75 mm"):
        assert dense_sim_grid(SIM, (128, 90)) == (1.75, pytest.approx(128 / 60))       # a crop keeps the pixel
    # an acquired pixel finer than the images' (a coarser output grid than the data): resolution 1, a warning
    # naming the ratio it computed, not N_im / N_im_pre_spiral (as a DICOM's AcquisitionMatrix is read, below)
    with pytest.warns(UserWarning, match=r"\(FOV / N_im_pre_spiral\) / the 90-pixel grid's pixel: the acquired "
                                         r"pixel \(1.86667 mm\) is finer than the images' pixel \(2.22222 mm\)"):
        assert dense_sim_grid({**SIM, "N_im_pre_spiral": 120, "output_dim": {"sizes": [90], "FOVs": [200]}},
                              (90, 90)) == (pytest.approx(200 / 90), DEFAULT_RESOLUTION_PX)
    # no N_im_pre_spiral: resolution 1, and a warning that says how to give it
    sim = {k: v for k, v in SIM.items() if k != "N_im_pre_spiral"}
    with pytest.warns(UserWarning, match=r"no sim_params.N_im_pre_spiral.*--resolution-px"):
        assert dense_sim_grid(sim, (128, 128)) == (1.75, DEFAULT_RESOLUTION_PX)
    # a config whose output_dim gives the N_im grid another FOV: FOV / N_im, as the dataset's README says, and a warning
    with pytest.warns(UserWarning, match=r"output_dim gives the N_im grid \(128 pixels\) a field of view of 200 mm"):
        px, _ = dense_sim_grid({**SIM, "output_dim": {"sizes": [128], "FOVs": [200]}}, (128, 128))
    assert px == pytest.approx(224 / 128)


def test_phases_that_are_not_frames_of_images_are_an_error_naming_their_file(tmp_path):
    folder = write_case_folder(tmp_path / "c", n=24)
    np.save(folder / "phase_x.npy", np.zeros((24, 24), np.float32))
    np.save(folder / "phase_y.npy", np.zeros((24, 24), np.float32))
    with pytest.raises(ValueError, match=r"phase_x.npy: expected \(frames, rows, columns\) phases"):
        read_dense_sim(folder)


@given(n_out=st.integers(8, 160), fov_out=st.floats(50.0, 400.0), n_acq=st.integers(4, 64))
def test_the_acquired_pixel_in_mm_does_not_depend_on_the_output_grid(n_out, fov_out, n_acq):
    sim = {"FOV": [224.0, 224.0, 8], "N_im": 128, "N_im_pre_spiral": n_acq,
           "output_dim": {"sizes": [128, n_out], "FOVs": [[224.0, 224.0, 8], [fov_out, fov_out, 8]]}}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        px_mm, res = dense_sim_grid(sim, (n_out, n_out))
    acquired_mm = 224.0 / n_acq
    assert px_mm == pytest.approx((fov_out if n_out != 128 else 224.0) / n_out)
    finer = acquired_mm < px_mm * (1 - 1e-12)
    if finer:                                   # images resampled coarser than their data: their own pixel
        assert res == DEFAULT_RESOLUTION_PX
    else:
        assert px_mm * res == pytest.approx(acquired_mm)
    assert any("is finer than the images' pixel" in str(w.message) for w in caught) == finer


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
    (None, 128, 128, DEFAULT_RESOLUTION_PX),
    ((0, 0, 0, 0), 128, 128, DEFAULT_RESOLUTION_PX)])          # no acquired size stated: 1, a warning
def test_dicom_resolution_is_the_image_matrix_over_the_acquisition_matrix(matrix, rows, cols, expected):
    ds = Dataset()
    ds.Rows, ds.Columns = rows, cols
    if matrix is not None:
        ds.AcquisitionMatrix = list(matrix)
    if matrix is not None and any(matrix):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert dicom_resolution_px(ds) == pytest.approx(expected)
    else:
        with pytest.warns(UserWarning, match="DICOM AcquisitionMatrix: expected four integers.*--resolution-px"):
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


def _ring_with_background(background, rng, resolution_px=2.13, frames=3):
    """A static ring of unit magnitude and zero phase on a background of the complex field ``background(rng)``
    (H, W, 2), blurred by the point spread of ``resolution_px``, with white complex noise of sd 0.02."""
    yy, xx = np.mgrid[0:64, 0:64].astype(float)
    r = np.hypot(xx - 31.6, yy - 32.3)
    ring = (r >= 10.0) & (r <= 19.0)                     # thick: the median of its magnitude is the tissue's
    sd = psf_sigma_px(resolution_px)
    phases, mags = [], []
    for _ in range(frames):
        bg = background(rng)
        enc = []
        for j in range(2):
            z = np.where(ring, 1.0 + 0j, bg[..., j])
            z = ndimage.gaussian_filter(z.real, sd) + 1j * ndimage.gaussian_filter(z.imag, sd)
            enc.append(z + 0.02 * (rng.standard_normal(z.shape) + 1j * rng.standard_normal(z.shape)) / np.sqrt(2))
        phases.append([np.angle(e) for e in enc])
        mags.append(np.abs(enc[0]))
    return make_dense_case(np.transpose(np.array(phases), (1, 0, 2, 3)), np.array(mags),
                           np.stack([ring] * (frames + 1)), 1.75, 0.1, 0.02 * (1 + np.arange(frames)),
                           resolution_px=resolution_px)


@pytest.mark.parametrize("seed", range(6))
def test_an_incoherent_background_mixes_in_nothing(seed):
    # random phase in every pixel (correlated over the acquired resolution, as a reconstruction's floor is),
    # its magnitude 0.3 of the tissue's: large pixel by pixel, no coherent level
    def incoherent(rng):
        z = rng.standard_normal((64, 64, 2)) + 1j * rng.standard_normal((64, 64, 2))
        z = ndimage.gaussian_filter(z.real, (0.8, 0.8, 0)) + 1j * ndimage.gaussian_filter(z.imag, (0.8, 0.8, 0))
        return 0.3 * z / np.sqrt(np.mean(np.abs(z) ** 2))
    case = _ring_with_background(incoherent, np.random.default_rng(seed))
    outside = ~ndimage.binary_dilation(case.frame_masks, iterations=3)
    assert np.median(case.magnitude[outside]) > 0.15                       # the floor is there, pixel by pixel
    assert np.array_equal(background_signal(case).signal, np.zeros_like(background_signal(case).signal))


@settings(max_examples=10, deadline=None)
@given(st.floats(0.1, 0.6), st.floats(-np.pi, np.pi), st.integers(0, 2 ** 16))
def test_a_coherent_background_is_read_back_with_its_amplitude_and_phase(amplitude, phase, seed):
    # one level of known amplitude and phase (the second encoding static) in the cavity and outside
    def coherent(rng):
        return np.stack([np.full((64, 64), amplitude * np.exp(1j * phase)), np.full((64, 64), amplitude + 0j)], -1)
    case = _ring_with_background(coherent, np.random.default_rng(seed))
    b = background_signal(case).signal
    outside = ~case.frame_masks
    assert np.allclose(b[..., 0][outside], amplitude * np.exp(1j * phase), atol=0.03)
    assert np.allclose(b[..., 1][outside], amplitude, atol=0.03)
