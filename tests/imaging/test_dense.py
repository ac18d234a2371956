"""DENSE images in: readers (DENSE-Sim folders, DICOM), the spec's noise, phase to Lagrangian displacement.

Ground truth from data we did not write: the two DENSE-Sim cases in ``$SFEM_FILTERS_DATA/dense_sim``
(default ``../shared/data``), with the strain the simulator computed; and analytic deformations
rendered as wrapped Eulerian phase.
"""
from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest
import yaml
from scipy import ndimage
from hypothesis import given, settings
from hypothesis import strategies as st

from helpers import write_dicom
from sfem_filters.imaging.conventional import conventional_analysis
from sfem_filters.imaging.confidence import local_phase_coherence
from sfem_filters.imaging.dense import (DenseCase, LagrangianDisplacement, add_complex_noise, carry_offsets,
                                        estimate_noise_sd, extend_field, interpolation_variance_factor,
                                        make_dense_case, phase_quality, phase_to_displacement,
                                        read_dense_dicom, read_dense_sim, reference_points, truth_at_points,
                                        unwrap_frames)
from sfem_filters.imaging.strain import global_curve

DATA = pathlib.Path(os.environ.get("SFEM_FILTERS_DATA",
                                  pathlib.Path(__file__).resolve().parents[3] / "shared" / "data"))
DENSE_SIM = DATA / "dense_sim"
CASES = ["invivo_subject_1", "phantom_subject_1"]
needs_data = pytest.mark.skipif(not DENSE_SIM.is_dir(), reason=f"DENSE-Sim cases not found in {DENSE_SIM}")

KE = 0.1            # cycles/mm
PX = 1.75           # mm
RAD_PER_PX = 2 * np.pi * KE * PX


def wrap(a):
    return np.angle(np.exp(1j * a))


# ------------------------------------------------------------------------------ synthetic cases
def render_affine(mats, centre=(19.3, 20.1), r_in=6.0, r_out=12.0, shape=(40, 40), directions=np.eye(2)):
    """Frames of a ring deformed by x = c + A (X - c), as wrapped Eulerian phase; and the exact Lagrangian u."""
    c = np.asarray(centre)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    pos = np.stack([xx, yy], axis=-1)
    ref = (np.hypot(xx - c[0], yy - c[1]) >= r_in) & (np.hypot(xx - c[0], yy - c[1]) <= r_out)
    phases, masks, exact = [], [ref], []
    X = reference_points(ref)
    for A in mats:
        pre = c + (pos - c) @ np.linalg.inv(A).T               # X of the tissue now at x
        u = pos - pre                                          # Eulerian displacement (pixels)
        r = np.hypot(*(pre - c).transpose(2, 0, 1))
        masks.append((r >= r_in) & (r <= r_out))
        phases.append([wrap(RAD_PER_PX * (u @ d)) for d in directions])
        exact.append((X - c) @ (A - np.eye(2)).T)
    phases = np.transpose(np.array(phases), (1, 0, 2, 3))
    F = len(mats)
    case = make_dense_case(phases, np.ones((F,) + shape), np.stack(masks), PX, KE, 0.015 * (1 + np.arange(F)),
                           directions=directions)
    return case, np.array(exact)


def affine_sequence(n=5, stretch=0.3, turn_deg=12.0):
    out = []
    for t in np.linspace(1.0 / n, 1.0, n):
        th = np.radians(turn_deg * t)
        R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        out.append(R @ np.diag([1 + stretch * t, 1 - 0.4 * stretch * t]))
    return out


def write_case_folder(folder: pathlib.Path, F=3, n=24, ke=0.1, **override):
    """A small DENSE-Sim-like case folder (a still ring, with a known phase)."""
    folder.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[0:n, 0:n]
    ring = (np.hypot(xx - 11.5, yy - 11.5) >= 4) & (np.hypot(xx - 11.5, yy - 11.5) <= 9)
    arrays = {"phase_x.npy": np.full((F, n, n), 0.3, np.float32), "phase_y.npy": np.full((F, n, n), -0.2, np.float32),
              "magnitude.npy": np.ones((F, n, n), np.float32),
              "LV_mask_time_lowres.npy": np.stack([ring] * (F + 1)),
              "GT_Ecc.npy": np.where(ring, 0.0, np.nan)[None].repeat(F, 0).astype(np.float32),
              "GT_Err.npy": np.where(ring, 0.0, np.nan)[None].repeat(F, 0).astype(np.float32)}
    arrays.update({k: v for k, v in override.items() if k.endswith(".npy")})
    for name, arr in arrays.items():
        if arr is not None:
            np.save(folder / name, arr)
    cfg = {"sim_params": {"FOV": [n * 1.75, n * 1.75, 8], "N_im": n, "N_im_pre_spiral": n, "ke": ke,
                          "tt": [0.0] + [22.5 + 15 * f for f in range(F + 2)]}}
    (folder / "config.yaml").write_text(yaml.safe_dump(cfg))
    return folder


# --------------------------------------------------------------------------------- DENSE-Sim reader
@needs_data
@pytest.mark.parametrize("name, frames, pixels", [("invivo_subject_1", 62, 867), ("phantom_subject_1", 40, 976)])
def test_read_dense_sim_as_published(name, frames, pixels):
    case = read_dense_sim(DENSE_SIM / name)
    assert isinstance(case, DenseCase)
    assert case.phases.shape == (2, frames, 128, 128) and case.magnitude.shape == (frames, 128, 128)
    assert case.masks.shape == (frames + 1, 128, 128) and case.reference_mask.sum() == pixels
    assert case.pixel_size_mm == pytest.approx(1.75) and case.pixel_size_m == pytest.approx(1.75e-3)
    assert case.ke_per_m == pytest.approx(100.0)
    assert case.frame_times_s[0] == pytest.approx(0.0225) and np.allclose(np.diff(case.frame_times_s), 0.015)
    ecc, err = truth_at_points(case)
    assert ecc.shape == (frames, pixels) and np.isfinite(ecc).all() and np.isfinite(err).all()


def test_read_case_folder_and_its_errors(tmp_path):
    case = read_dense_sim(write_case_folder(tmp_path / "ok"))
    assert case.n_frames == 3 and np.allclose(case.phases[0], 0.3) and case.has_truth
    assert case.frame_times_s == pytest.approx([0.0225, 0.0375, 0.0525])
    no_truth = write_case_folder(tmp_path / "nt")
    os.remove(no_truth / "GT_Ecc.npy")
    assert not read_dense_sim(no_truth).has_truth
    with pytest.raises(ValueError, match="case: expected ground-truth"):
        truth_at_points(read_dense_sim(no_truth))
    missing = write_case_folder(tmp_path / "m")
    os.remove(missing / "phase_y.npy")
    with pytest.raises(FileNotFoundError, match="phase_y.npy"):
        read_dense_sim(missing)
    with pytest.raises(FileNotFoundError, match="path: expected a DENSE-Sim case folder"):
        read_dense_sim(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="phase_y.npy: expected the shape"):
        read_dense_sim(write_case_folder(tmp_path / "s", **{"phase_y.npy": np.zeros((3, 24, 23), np.float32)}))
    with pytest.raises(ValueError, match="masks: expected the reference mask"):
        read_dense_sim(write_case_folder(tmp_path / "e", **{"LV_mask_time_lowres.npy": np.zeros((4, 24, 24), bool)}))
    with pytest.raises(ValueError, match="phases: expected wrapped phases"):
        read_dense_sim(write_case_folder(tmp_path / "p", **{"phase_x.npy": np.full((3, 24, 24), 4.0, np.float32)}))
    with pytest.raises(ValueError, match="ke"):
        read_dense_sim(write_case_folder(tmp_path / "k", ke=None))
    with pytest.raises(ValueError, match="ke_cycles_per_mm: expected a positive"):
        read_dense_sim(write_case_folder(tmp_path / "k0", ke=0.0))
    cfg = write_case_folder(tmp_path / "c")
    (cfg / "config.yaml").write_text(yaml.safe_dump({"sim_params": {"FOV": [42, 42, 8], "N_im": 24, "tt": [0, 1]}}))
    with pytest.raises(ValueError, match="sim_params.ke"):
        read_dense_sim(cfg)


def test_make_dense_case_errors_name_the_argument():
    ring = np.zeros((8, 8), bool)
    ring[2:6, 2:6] = True
    good = dict(phases=np.zeros((2, 2, 8, 8)), magnitude=np.ones((2, 8, 8)), masks=np.stack([ring] * 3),
                pixel_size_mm=1.75, ke_cycles_per_mm=0.1, frame_times_s=[0.01, 0.02])
    make_dense_case(**good)
    for key, value, msg in [("magnitude", np.ones((2, 8, 7)), "magnitude: expected shape"),
                            ("masks", np.stack([ring] * 2), "masks: expected shape"),
                            ("phases", np.full((2, 2, 8, 8), np.pi + 1e-3), "phases: expected wrapped"),
                            ("ke_cycles_per_mm", None, "ke_cycles_per_mm: expected the DENSE"),
                            ("ke_cycles_per_mm", -0.1, "ke_cycles_per_mm"),
                            ("frame_times_s", [0.02, 0.01], "frame_times_s: expected increasing"),
                            ("directions", [[1, 0], [1, 0]], "directions: expected two independent"),
                            ("masks", np.stack([ring, ring, np.zeros_like(ring)]), r"frame\(s\) \[1\]")]:
        with pytest.raises(ValueError, match=msg):
            make_dense_case(**{**good, key: value})
    ok = make_dense_case(**{**good, "phases": np.full((2, 2, 8, 8), np.pi + 5e-5)})     # float rounding tolerated
    assert ok.phases.max() > np.pi


# ------------------------------------------------------------------------------------ DICOM reader
def test_dicom_reader_matches_the_arrays(tmp_path):
    case, exact = render_affine(affine_sequence(n=3, stretch=0.1, turn_deg=4), shape=(40, 40))
    stored = np.round((case.phases + np.pi) / (2 * np.pi) * 4095).astype(int)          # 12-bit 0..4095
    rescaled = 2.0 * stored - 4096.0                                                    # RescaleSlope 2, -4096
    expected = -np.pi + 2 * np.pi * (rescaled + 4096) / 8190.0
    dirs = []
    for j, name in enumerate(["px", "py"]):
        d = tmp_path / name
        d.mkdir()
        for f in (2, 0, 1):                                                # written out of order
            write_dicom(d / f"im{f}.dcm", stored[j, f], 22.5 + 15 * f, f + 1)
        (d / "notes.txt").write_text("not a DICOM file")
        dirs.append(d)
    mdir = tmp_path / "mag"
    mdir.mkdir()
    for f in range(3):
        write_dicom(mdir / f"m{f}.dcm", np.full((40, 40), 1000), 22.5 + 15 * f, f + 1, slope=1.0, intercept=0.0)
    got = read_dense_dicom(dirs, mdir, masks=case.masks, ke_cycles_per_mm=KE, phase_range=(-4096, 4094))
    assert np.allclose(got.phases, expected, atol=1e-12)
    assert np.max(np.abs(got.phases - case.phases)) < 2 * np.pi / 4095
    assert got.pixel_size_mm == pytest.approx(1.75) and got.ke_per_m == pytest.approx(100.0)
    assert got.frame_times_s == pytest.approx([0.0225, 0.0375, 0.0525])
    assert np.allclose(got.magnitude, 1000.0)
    d = phase_to_displacement(got)
    assert np.nanmax(np.abs(d.displacement - exact)) < 0.05          # 12-bit quantisation of the phase
    with pytest.raises(ValueError, match="ke_cycles_per_mm: expected the DENSE"):
        read_dense_dicom(dirs, mdir, masks=case.masks, ke_cycles_per_mm=None, phase_range=(-4096, 4094))
    with pytest.raises(ValueError, match=r"phase_dirs\[0\]: expected phases in radians.*phase_range"):
        read_dense_dicom(dirs, mdir, masks=case.masks, ke_cycles_per_mm=KE)
    with pytest.raises(FileNotFoundError, match="magnitude_dir"):
        read_dense_dicom(dirs, tmp_path / "absent", masks=case.masks, ke_cycles_per_mm=KE, phase_range=(-4096, 4094))
    with pytest.raises(ValueError, match="masks: expected shape"):
        read_dense_dicom(dirs, mdir, masks=case.masks[:3], ke_cycles_per_mm=KE, phase_range=(-4096, 4094))


# ------------------------------------------------------------------------------------------ noise
def test_complex_noise_follows_the_spec_rng_order():
    F, H, W = 2, 3, 4
    r = np.random.default_rng(7)
    ph = r.uniform(-3, 3, (2, F, H, W))
    mag = r.uniform(1, 2, (F, H, W))
    masks = np.zeros((F + 1, H, W), bool)
    masks[0, :, :2] = True                     # the reference mask must not enter the noise level
    masks[1:, 1, 1:3] = True
    case = make_dense_case(ph, mag, masks, 1.75, 0.1, [0.01, 0.02])
    noisy = add_complex_noise(case, snr=5.0, seed=3)
    sd = mag[:, 1, 1:3].mean() / 5.0           # masks[1:] only: 4 pixels
    rng = np.random.default_rng(3)
    a_x, b_x = rng.standard_normal((F, H, W)), rng.standard_normal((F, H, W))      # phase_x: real, then imaginary
    a_y, b_y = rng.standard_normal((F, H, W)), rng.standard_normal((F, H, W))      # then phase_y
    want_x = np.angle(mag * np.exp(1j * ph[0]) + sd * (a_x + 1j * b_x)).astype(np.float32)
    want_y = np.angle(mag * np.exp(1j * ph[1]) + sd * (a_y + 1j * b_y)).astype(np.float32)
    assert np.array_equal(noisy.phases[0], want_x) and np.array_equal(noisy.phases[1], want_y)
    swapped = np.angle(mag * np.exp(1j * ph[0]) + sd * (a_y + 1j * b_y)).astype(np.float32)
    assert not np.allclose(noisy.phases[0], swapped)
    assert noisy.magnitude is case.magnitude and noisy.masks is case.masks
    assert np.array_equal(add_complex_noise(case, 5.0, 3).phases, noisy.phases)
    with pytest.raises(ValueError, match="snr"):
        add_complex_noise(case, 0.0, 1)


# ------------------------------------------------------------------------------------- unwrapping
def _two_pieces(shape=(24, 30)):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    m = np.zeros(shape, bool)
    m[3:20, 2:12] = True
    m[5:21, 16:28] = True
    return m, yy, xx


@settings(max_examples=30, deadline=None)
@given(k1=st.integers(-3, 3), k2=st.integers(-3, 3), slope=st.floats(-0.6, 0.6), shift=st.floats(-2.0, 2.0))
def test_piece_offsets_do_not_matter(k1, k2, slope, shift):
    m, yy, xx = _two_pieces()
    prev = np.where(m, slope * (xx - 15) + shift, np.nan)
    cur = prev + 0.3 * np.sin(yy / 5.0)                          # a small change in time
    offset = np.zeros(m.shape)
    offset[:, :14] = 2 * np.pi * k1
    offset[:, 14:] = 2 * np.pi * k2
    base = carry_offsets(cur, m, prev)
    moved = carry_offsets(cur + offset, m, prev)
    assert np.allclose(base[m], moved[m], atol=1e-9)
    assert np.allclose(base[m], cur[m], atol=1e-9)                # the carried answer is the true one


@settings(max_examples=15, deadline=None)
@given(slope=st.floats(0.2, 0.9), twist=st.floats(-0.5, 0.5))
def test_unwrap_frames_recovers_phases_beyond_pi(slope, twist):
    m, yy, xx = _two_pieces()
    frames = np.array([s * (slope * (xx - 14) + twist * (yy - 12)) for s in np.linspace(0.1, 1.0, 6)])
    masks = np.stack([m] * 6)
    got = unwrap_frames(wrap(frames), masks)
    assert np.abs(frames).max() > np.pi or slope < 0.25
    assert np.allclose(got[masks], frames[masks], atol=1e-9) and np.isnan(got[~masks]).all()


# ----------------------------------------------------------------------- phase to displacement
@pytest.mark.parametrize("turn", [0.0, 30.0])
def test_affine_deformation_is_recovered_to_a_hundredth_of_a_pixel(turn):
    th = np.radians(turn)
    dirs = np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])
    case, exact = render_affine(affine_sequence(), directions=dirs)
    assert np.abs(exact).max() * RAD_PER_PX > np.pi                   # the phase wraps
    d = phase_to_displacement(case)
    assert d.n_untracked == 0
    assert np.abs(d.displacement - exact).max() < 1e-2
    assert d.points.shape == (case.reference_mask.sum(), 2) and d.frame_times_s.shape == (case.n_frames,)


def test_extend_field_is_exact_for_an_affine_field_and_goes_two_rings():
    m, yy, xx = _two_pieces()
    f = np.stack([0.3 + 0.1 * xx - 0.05 * yy, -1 + 0.02 * xx + 0.2 * yy], axis=-1)
    ext = extend_field(f, m, rings=2)
    known = np.isfinite(ext).all(-1)
    assert np.array_equal(known, ndimage.binary_dilation(m, np.ones((3, 3), bool), iterations=2))
    assert np.allclose(ext[known], f[known], atol=1e-9)


def test_untracked_points_are_counted_not_hidden():
    case, _ = render_affine(affine_sequence(n=2, stretch=0.05, turn_deg=2))
    masks = case.masks.copy()
    masks[2, :, :19] = False                                         # frame 1 has lost its left half
    cut = make_dense_case(case.phases, case.magnitude, masks, PX, KE, case.frame_times_s)
    d = phase_to_displacement(cut)
    bad = ~np.isfinite(d.displacement).all(axis=2)
    assert d.n_untracked == int(bad.sum()) > 0 and not bad[0].any()
    assert np.isnan(d.sd[bad]).all() and np.isnan(d.confidence[bad]).all()
    assert np.isfinite(d.sd[~bad]).all() and np.isfinite(d.confidence[~bad]).all()


def test_noise_sd_and_confidence_follow_the_noise():
    case, exact = render_affine(affine_sequence(n=3, stretch=0.1, turn_deg=4))
    mag = np.ones(case.magnitude.shape)
    mag[:, :, 20:] = 2.0                                             # the right half is brighter
    case = make_dense_case(case.phases, mag, case.masks, PX, KE, case.frame_times_s)
    clean = phase_to_displacement(case)
    noisy_case = add_complex_noise(case, snr=12.0, seed=1)
    sd_true = mag[case.frame_masks].mean() / 12.0
    est = estimate_noise_sd(noisy_case.phases[0], noisy_case.magnitude, noisy_case.frame_masks)
    assert est == pytest.approx(sd_true, rel=0.15)
    d = phase_to_displacement(noisy_case)
    bright = d.points[:, 0] >= 22
    dim = d.points[:, 0] <= 17
    ratio = np.nanmedian(d.sd[:, dim]) / np.nanmedian(d.sd[:, bright])
    assert ratio == pytest.approx(2.0, rel=0.15)                     # sd ~ 1 / local magnitude
    err = d.displacement - exact
    for sel in (bright, dim):                                        # each datum's error over its reported sd
        assert np.nanstd(err[:, sel] / d.sd[:, sel]) == pytest.approx(1.0, abs=0.1)
        # the pixels' sd is larger by the interpolation's 1 / sqrt(sum w^2), 3/2 on average
        assert np.nanstd(err[:, sel]) / np.nanmedian(d.pixel_sd[:, sel]) == pytest.approx(0.67, abs=0.08)
    assert np.nanmedian(clean.confidence) > 0.999 > np.nanmedian(d.confidence)
    assert np.nanmean(d.confidence[:, dim]) < np.nanmean(d.confidence[:, bright])


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_reported_sd_is_the_actual_error(seed):
    case, exact = render_affine(affine_sequence(n=3, stretch=0.1, turn_deg=4))
    d = phase_to_displacement(add_complex_noise(case, snr=12.0, seed=seed))
    z = (d.displacement - exact) / d.sd
    assert np.nanstd(z) == pytest.approx(1.0, abs=0.1)
    assert np.nanmean(z ** 2 > 1.96 ** 2) == pytest.approx(0.05, abs=0.025)   # Gaussian tails, not a mixture


def test_a_mean_over_tracks_has_the_error_of_independent_pixels():
    """Neighbouring tracks interpolate shared pixels: a mean over a patch of them (what a smooth fit
    sees) has the variance of independent data at ``pixel_sd``, about twice that at ``sd``."""
    case, exact = render_affine(affine_sequence(n=3, stretch=0.1, turn_deg=4))
    err2, by_sd, by_pixel = [], [], []
    for seed in range(6):
        d = phase_to_displacement(add_complex_noise(case, snr=12.0, seed=seed))
        err = d.displacement - exact
        patch = (d.points[:, 0] // 5) * 100 + d.points[:, 1] // 5          # 5 x 5 pixel patches
        for f in range(case.n_frames):
            for c in range(2):
                ok = np.isfinite(err[f, :, c])
                for k in np.unique(patch[ok]):
                    s = ok & (patch == k)
                    n = s.sum()
                    if n >= 20:
                        err2.append(err[f, s, c].mean() ** 2)
                        by_sd.append(np.mean(d.sd[f, s, c] ** 2) / n)
                        by_pixel.append(np.mean(d.pixel_sd[f, s, c] ** 2) / n)
    assert len(err2) > 200
    assert np.mean(err2) / np.mean(by_pixel) == pytest.approx(1.0, abs=0.2)
    assert np.mean(err2) / np.mean(by_sd) > 1.6                      # the data are not independent at sd


@settings(max_examples=50, deadline=None)
@given(st.floats(1.0, 8.0), st.floats(1.0, 8.0))
def test_interpolation_variance_factor_is_the_sum_of_squared_weights(x, y):
    weights = []
    for r in range(10):
        for c in range(10):
            impulse = np.zeros((10, 10))
            impulse[r, c] = 1.0
            weights.append(ndimage.map_coordinates(impulse, [[y], [x]], order=1)[0])
    assert sum(weights) == pytest.approx(1.0)
    assert interpolation_variance_factor([[x, y]])[0] == pytest.approx(float(np.sum(np.square(weights))))
    assert 0.25 - 1e-12 <= interpolation_variance_factor([[x, y]])[0] <= 1.0 + 1e-12


def test_pixel_sd_defaults_to_sd_and_must_match_it():
    sd = np.full((2, 3, 2), 0.1)
    args = dict(points=np.zeros((3, 2)), displacement=np.zeros((2, 3, 2)), sd=sd, confidence=np.ones((2, 3)),
                frame_times_s=np.array([0.1, 0.2]), n_untracked=0, noise_sd=np.ones(2))
    assert LagrangianDisplacement(**args).pixel_sd is sd
    with pytest.raises(ValueError, match="pixel_sd: expected the shape of sd"):
        LagrangianDisplacement(**args, pixel_sd=np.ones((2, 3)))


def test_phase_quality_ignores_strain_but_sees_noise():
    m = np.ones((1, 20, 20), bool)
    yy, xx = np.mgrid[0:20, 0:20]
    steep = wrap(0.9 * xx)[None]                                     # a strong phase gradient, no noise
    assert phase_quality(steep, m)[0, 2:-2, 2:-2].min() > 1 - 1e-12
    assert local_phase_coherence(steep)[0, 2:-2, 2:-2].max() < 0.9     # the paper's LPC sees the gradient
    s = 0.3
    noisy = wrap(steep + s * np.random.default_rng(0).standard_normal(steep.shape))
    q = phase_quality(noisy, m)[0, 2:-2, 2:-2].mean()
    assert q == pytest.approx(np.exp(-s ** 2 / 2), abs=0.06)
    assert phase_quality(noisy, np.zeros_like(m)).max() == 0.0


# ------------------------------------------------------------------- ground truth from DENSE-Sim
# Noise-free cases, the conventional analysis without smoothing. The truth is computed on a finer
# grid and resampled (about a quarter pixel of offset, some anti-aliasing), and the simulator
# leaves a phase texture of 0.1-0.2 rad, so pixels are noisy (pixel RMSE 6-9 pp Ecc, 13-16 pp Err,
# measured); the global curves must follow the truth: stated tolerance, the largest error of the
# global curve over frames at most 1.5 pp (Ecc) and 4.5 pp (Err), measured 1.43 / 3.12 (in vivo)
# and 0.65 / 4.23 (phantom), and a correlation above 0.98 over frames.
@needs_data
@pytest.mark.parametrize("name", CASES)
def test_conventional_strain_follows_dense_sim_truth(name):
    case = read_dense_sim(DENSE_SIM / name)
    t_ecc, t_err = truth_at_points(case)
    a = conventional_analysis(case)
    assert a.tracks.n_untracked <= 0.001 * t_ecc.size
    g_ecc, g_err = global_curve(t_ecc), global_curve(t_err)
    assert np.nanmax(np.abs(a.global_Ecc - g_ecc)) < 0.015
    assert np.nanmax(np.abs(a.global_Err - g_err)) < 0.045
    assert np.corrcoef(a.global_Ecc, g_ecc)[0, 1] > 0.98 and np.corrcoef(a.global_Err, g_err)[0, 1] > 0.98
    ok = np.isfinite(a.strain.Ecc)
    assert np.sqrt(np.mean((a.strain.Ecc - t_ecc)[ok] ** 2)) < 0.10
    assert np.sqrt(np.mean((a.strain.Err - t_err)[ok] ** 2)) < 0.18
