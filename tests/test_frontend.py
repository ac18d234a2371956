"""Image front end: contours, shape tracking (Eqs. 35-37), phase coherence (Eqs. 38-39),
segmentation, readers, the observe command, and fusion of borders and velocity in the EKF."""
import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters import dense, frontend, synthetic
from sfem_filters.cli import main
from sfem_filters.confidence import (bending_energy, goodness_uniqueness, local_phase_coherence,
                                     match_confidence, velocity_coherence, weighted_std)
from sfem_filters.contours import check_myocardium_mask, curvature, mask_borders, resample_closed, signed_area
from sfem_filters.datasets import load_sequence, make_sequence
from sfem_filters.filters import cyclic_estimate
from sfem_filters.phase_contrast import sample_bilinear, sample_velocity, synthetic_phase_contrast
from sfem_filters.readers import make_image_series, read_images
from sfem_filters.segmentation import dice, segment_sequence
from sfem_filters.tracking import TrackingOptions, contour_curvature, smooth_vectors, track_masks


def ring(shape=(48, 48), centre=(23.5, 23.5), r_in=8.0, r_out=13.0, bump=0.0, angle=0.0):
    """A ring mask; ``bump`` adds a 3-lobed wobble to both radii (so the shape has features)."""
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    dx, dy = xx - centre[0], yy - centre[1]
    th = np.arctan2(dy, dx) - angle
    r = np.hypot(dx, dy)
    w = 1.0 + bump * np.cos(3 * th)
    return (r >= r_in * w) & (r <= r_out * w)


# ----------------------------------------------------------------------------- contours
def test_circle_contour_curvature_and_orientation():
    b = mask_borders(ring(shape=(96, 96), centre=(47.5, 47.5), r_in=20, r_out=30), 96, 128, smooth=2.0)
    assert signed_area(b.endo) > 0 and signed_area(b.epi) > 0
    # marching squares at level 1/2 puts the borders half a pixel outside the tissue pixels;
    # the staircase makes single samples noisy, the smoothed curvature is close to 1/r
    for xy, r in ((b.endo, 19.5), (b.epi, 30.5)):
        assert abs(np.mean(curvature(xy)) - 1 / r) < 0.05 / r
        assert abs(np.median(contour_curvature(xy, 3.0)) - 1 / r) < 0.15 / r
    assert np.allclose(np.linalg.norm(b.centre - 47.5), 0, atol=0.3)


def test_curvature_of_exact_circle():
    th = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    xy = np.column_stack([3 + 7 * np.cos(th), -2 + 7 * np.sin(th)])
    assert np.allclose(curvature(xy), 1 / 7, rtol=1e-3)
    assert np.allclose(curvature(xy[::-1]), -1 / 7, rtol=1e-3)


def test_resample_closed_is_equally_spaced():
    sq = np.array([[0, 0], [4, 0], [4, 4], [0, 4]], float)
    r = resample_closed(sq, 16)
    seg = np.linalg.norm(np.diff(np.vstack([r, r[:1]]), axis=0), axis=1)
    assert np.allclose(seg, 1.0)


@pytest.mark.parametrize("mask, message", [
    (np.zeros((10, 10), bool), "expected some tissue"),
    (ring() | (np.mgrid[0:48, 0:48][0] > 45), "one connected piece"),
    (np.pad(np.ones((5, 5), bool), 3), "exactly one cavity"),
    (np.zeros((3, 4, 5), bool), "expected a 2D mask"),
])
def test_bad_masks_are_named(mask, message):
    with pytest.raises(ValueError, match=message):
        check_myocardium_mask(mask)


# --------------------------------------------------------------- confidence (Eqs. 35-37)
def test_bending_energy_and_measures():
    assert bending_energy(0.1, 0.3) == pytest.approx(0.02)
    e = np.array([[4.0, 1.0, 4.0, 4.0], [1.0, 1.0, 1.0, 1.0]])
    best, m_g, m_u = goodness_uniqueness(e)
    assert best[0] == 1 and m_g[0] == 1.0 and m_u[0] == pytest.approx(1 / 3.25)
    assert m_u[1] == 1.0                      # no candidate stands out: not unique
    assert match_confidence(0.0, 0.0, 1.0) == 1.0


@settings(max_examples=50, deadline=None)
@given(st.floats(0, 1e3), st.floats(0, 1), st.floats(1e-6, 1e3), st.floats(0, 10))
def test_confidence_in_unit_interval_and_monotone(m_g, m_u, scale, dg):
    c = match_confidence(m_g, m_u, scale)
    assert 0.0 < c <= 1.0
    assert match_confidence(m_g + dg, m_u, scale) <= c
    assert match_confidence(m_g, min(m_u + dg / 10, 1.0), scale) <= c


def test_weighted_std_follows_one_minus_confidence():
    s = weighted_std(np.array([0.0, 0.5, 1.0]), scale=2.0, floor=0.1)
    assert np.allclose(s ** 2, 0.01 + 4.0 * np.array([1.0, 0.5, 0.0]))
    with pytest.raises(ValueError, match="floor"):
        weighted_std([0.5], 1.0, 0.0)
    with pytest.raises(ValueError, match=r"confidence: expected values in \[0, 1\]"):
        weighted_std([1.5], 1.0, 0.1)


def test_smooth_vectors():
    v = np.tile([0.3, -0.2], (20, 1))
    assert np.allclose(smooth_vectors(v, np.ones(20), 10.0), v)
    v2 = v.copy()
    v2[5] = [5.0, 5.0]                         # an outlier with no confidence follows its neighbours
    w = np.ones(20)
    w[5] = 0.0
    assert np.allclose(smooth_vectors(v2, w, 10.0), v, atol=1e-12)


# ------------------------------------------------------------------ tracking (Eqs. 35-37)
@pytest.mark.parametrize("motion", ["translate", "rotate"])
def test_tracking_recovers_rigid_motion_of_a_featured_ring(motion):
    F = 6
    shift = np.array([0.6, -0.4])
    if motion == "translate":
        masks = np.stack([ring(centre=(23.5 + shift[0] * t, 23.5 + shift[1] * t), bump=0.2) for t in range(F)])
    else:
        masks = np.stack([ring(bump=0.2, angle=0.04 * t) for t in range(F)])
    tr = track_masks(masks, TrackingOptions(window=3, regularisation=4.0))
    P0 = tr.points
    if motion == "translate":
        truth = np.stack([np.tile(shift * t, (len(P0), 1)) for t in range(F)])
    else:
        c = np.array([23.5, 23.5])
        truth = []
        for t in range(F):
            a = 0.04 * t
            R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
            truth.append((P0 - c) @ R.T + c - P0)
        truth = np.stack(truth)
    err = np.linalg.norm(tr.displacement - truth, axis=2)
    motion_size = np.linalg.norm(truth[-1], axis=1).mean()
    assert motion_size > 0.9
    assert np.sqrt(np.mean(err[-1] ** 2)) < 0.5 * motion_size
    assert np.all((tr.step_confidence >= 0) & (tr.step_confidence <= 1))
    assert np.all(np.diff(tr.sigma, axis=0) > 0)          # tracking error accumulates along the chain


def test_confidence_is_lower_on_featureless_arcs():
    """Uniqueness: on a circle every candidate fits, on a lobed ring the lobes pin the match."""
    F = 4
    circ = track_masks(np.stack([ring(shape=(64, 64), centre=(31.5 + 0.5 * t, 31.5), r_in=12, r_out=18)
                                 for t in range(F)]))
    lobed = track_masks(np.stack([ring(shape=(64, 64), centre=(31.5 + 0.5 * t, 31.5), r_in=12, r_out=18,
                                       bump=0.25) for t in range(F)]))
    assert np.median(lobed.m_u[1:]) < np.median(circ.m_u[1:])


def test_track_masks_names_bad_frame():
    masks = np.stack([ring(), ring(), np.zeros((48, 48), bool)])
    with pytest.raises(ValueError, match=r"masks\[2\]: expected some tissue"):
        track_masks(masks)


# --------------------------------------------------------------- phase coherence (38-39)
def test_lpc_is_one_for_smooth_phase_and_low_for_random():
    yy, xx = np.mgrid[0:20, 0:20]
    smooth = 0.01 * xx + 0.02 * yy
    assert np.allclose(local_phase_coherence(smooth)[2:-2, 2:-2], 1.0, atol=1e-3)
    rnd = np.random.default_rng(0).uniform(-np.pi, np.pi, (60, 60))
    assert np.mean(local_phase_coherence(rnd)) < 0.45


def _synthetic_pc(seed=1, n_frames=12, noise_mid=0.05, noise_border=1.0):
    seq, truth = synthetic.annulus_sequence(effect="active_polar", seed=seed, return_truth=True, beta=0.03,
                                            n_frames=n_frames)
    H, W = seq.reference_mask.shape
    s = seq.pixel_spacing
    c = np.rint(seq.points).astype(int)
    vimg = np.zeros((seq.n_frames, H, W, 2))
    vimg[:, c[:, 1], c[:, 0]] = truth["velocity"] * s
    vmax = float(np.abs(vimg).max())
    venc = 2.0 * vmax
    depth = frontend.pixel_depth(seq.reference_mask)
    pc = synthetic_phase_contrast(vimg, seq.reference_mask, venc, noise_mid * vmax, noise_border * vmax, depth, seed)
    return seq, truth, pc, venc, vmax, depth


def test_lpc_high_at_midwall_low_at_borders_and_outside():
    seq, truth, pc, venc, vmax, depth = _synthetic_pc()
    lpc = velocity_coherence(pc, venc)
    m = seq.reference_mask
    mid = lpc[:, m & (np.abs(depth - 0.5) <= 0.15)].mean()
    border = lpc[:, m & (np.abs(depth - 0.5) >= 0.3)].mean()
    outside = lpc[:, ~m].mean()
    assert mid > 0.8 and mid > border + 0.2 and border > outside


def test_lpc_weighting_lowers_the_filters_velocity_error():
    """(1 - LPC)-weighted R against a uniform R (every velocity at the median of the weighted
    standard deviations: one nominal noise level for the acquisition, as without confidences):
    the filter's velocity estimate is closer to the truth with the
    weighting, and either is closer than no velocity data at all."""
    seq, truth, pc, venc, vmax, depth = _synthetic_pc(noise_mid=0.05, noise_border=1.0)
    vel = sample_velocity(pc, seq.points, venc, seq.pixel_spacing, floor=0.01 * vmax)
    errors = {}
    for weighting in ("lpc", "uniform", "none"):
        setup = dense.prepare(seq, 8)
        mid = np.arange(seq.n_points)          # velocity at every tissue pixel, borders included
        if weighting != "none":
            setup.velocity_points = mid
            setup.velocity = vel.velocity[:, mid]
            sd = vel.sigma[:, mid]
            setup.velocity_sigma = sd if weighting == "lpc" else np.full_like(sd, np.median(sd))
        model, y = dense.build_model(setup, (), "penalty", "none", beta=0.03)
        res = cyclic_estimate(model, y, max_loops=1, progress=False)
        V = model.velocities(res.states).reshape(seq.n_frames, -1, 2) / seq.pixel_spacing
        errors[weighting] = np.sqrt(np.mean((V[1:, mid] - truth["velocity"][1:, mid]) ** 2))
    print(errors)
    assert errors["lpc"] < 0.95 * errors["uniform"] and errors["uniform"] < errors["none"], errors


def test_sample_bilinear_exact_on_linear_fields_and_checks_bounds():
    yy, xx = np.mgrid[0:10, 0:12]
    img = 2.0 * xx - 3.0 * yy + 1.0
    pts = np.array([[3.25, 4.5], [0.0, 0.0], [11.0, 9.0]])
    assert np.allclose(sample_bilinear(img, pts), 2 * pts[:, 0] - 3 * pts[:, 1] + 1)
    with pytest.raises(ValueError, match="points: expected positions inside"):
        sample_bilinear(img, [[12.5, 1.0]])


# --------------------------------------------------------- fusion of borders and velocity
def test_velocity_fusion_beats_borders_alone_on_heldout_points():
    """Known answer: masks drawn from the true motion, tracked; velocities with border noise."""
    seq, truth, pc, venc, vmax, depth = _synthetic_pc(seed=2, n_frames=12)
    masks = synthetic.deformed_masks(seq, truth["displacement"])
    tracks = track_masks(masks, TrackingOptions(window=4, regularisation=4.0))
    vel = sample_velocity(pc, seq.points, venc, seq.pixel_spacing, floor=0.01 * vmax)
    reference = make_sequence(seq.points, truth["displacement"], frame_interval=seq.frame_interval,
                              pixel_spacing=seq.pixel_spacing, reference_mask=seq.reference_mask)
    out = frontend.compare_fusion(reference, tracks, vel, max_loops=1, beta=0.03)
    a, b = out["borders"], out["borders+velocity"]
    print({k: round(v["heldout_rmse_px"], 3) for k, v in out.items()})
    assert a["n_heldout"] == b["n_heldout"] and b["n_velocity_points"] > 0
    assert b["heldout_rmse_px"] < 0.85 * a["heldout_rmse_px"], out


# ---------------------------------------------------------------------------- segmentation
def test_segmentation_of_noisy_ring_images():
    rng = np.random.default_rng(0)
    masks = np.stack([ring(centre=(23.5 + 0.3 * t, 23.5), bump=0.1) for t in range(4)])
    images = 0.2 + 0.8 * masks + 0.15 * rng.standard_normal(masks.shape)
    seg = segment_sequence(images)
    assert min(dice(s, m) for s, m in zip(seg, masks)) > 0.9


# --------------------------------------------------------------------------------- readers
def test_npz_reader_and_errors(tmp_path):
    masks = np.stack([ring()] * 3)
    p = tmp_path / "m.npz"
    np.savez(p, masks=masks, pixel_spacing=1.5e-3, frame_interval=0.04)
    s = read_images(p)
    assert s.n_frames == 3 and s.pixel_spacing == 1.5e-3 and s.frame_interval == 0.04
    with pytest.raises(ValueError, match="venc: velocity images need"):
        make_image_series(masks=masks, velocity=np.zeros(masks.shape + (2,)))
    with pytest.raises(ValueError, match="at least 2 frames"):
        make_image_series(masks=masks[:1])
    bad = tmp_path / "bad.npz"
    bad.write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable numpy image file"):
        read_images(bad)
    other = tmp_path / "m.txt"
    other.write_text("x")
    with pytest.raises(ValueError, match="expected a DICOM directory"):
        read_images(other)


def test_dicom_series_reader(tmp_path):
    pydicom = pytest.importorskip("pydicom")
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    img = (ring().astype(np.uint16) * 1000)
    for k in (2, 0, 1):                                    # written out of order on purpose
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.4"
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = FileDataset(str(tmp_path / f"f{k}.dcm"), {}, file_meta=meta, preamble=b"\0" * 128)
        ds.Rows, ds.Columns = img.shape
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 0
        ds.PixelSpacing = [1.25, 1.25]
        ds.TriggerTime = 40.0 * k
        ds.InstanceNumber = k + 1
        ds.PixelData = np.roll(img, k, axis=1).tobytes()
        ds.save_as(str(tmp_path / f"f{k}.dcm"), enforce_file_format=True)
    s = read_images(tmp_path)
    assert s.n_frames == 3
    assert s.pixel_spacing == pytest.approx(1.25e-3)
    assert s.frame_interval == pytest.approx(0.040)
    assert np.array_equal(s.magnitude[1], np.roll(img, 1, axis=1))       # sorted by trigger time


def test_nifti_reader(tmp_path):
    nib = pytest.importorskip("nibabel")
    data = np.stack([ring().T.astype(float) * (t + 1) for t in range(4)], axis=-1)     # (X, Y, T)
    im = nib.Nifti1Image(data[:, :, None, :], np.diag([1.4, 1.4, 8.0, 1.0]))
    im.header.set_xyzt_units("mm", "msec")
    im.header["pixdim"][4] = 35.0
    path = tmp_path / "cine.nii.gz"
    nib.save(im, str(path))
    s = read_images(path)
    assert s.n_frames == 4
    assert s.pixel_spacing == pytest.approx(1.4e-3)
    assert s.frame_interval == pytest.approx(0.035)
    assert np.array_equal(s.magnitude[2] > 0, ring())


# ------------------------------------------------------------------------- observe command
def test_observe_command_writes_a_loadable_sequence_and_figures(tmp_path):
    seq, truth, pc, venc, vmax, depth = _synthetic_pc(n_frames=6)
    masks = synthetic.deformed_masks(seq, truth["displacement"])
    src = tmp_path / "images.npz"
    np.savez(src, masks=masks, velocity=pc, venc=venc, pixel_spacing=seq.pixel_spacing,
             frame_interval=seq.frame_interval)
    out = tmp_path / "obs" / "seq.npz"
    figs = tmp_path / "figs"
    assert main(["observe", str(src), "--out", str(out), "--figures", str(figs)]) == 0
    s = load_sequence(out)
    border = s.point_kind < 2
    assert np.all(np.isfinite(s.displacement[:, border])) and np.all(np.isnan(s.displacement[:, ~border]))
    assert np.all(np.isfinite(s.velocity[:, ~border])) and np.all(np.isnan(s.velocity[:, border]))
    assert np.all((s.confidence[:, border] >= 0) & (s.confidence[:, border] <= 1))
    assert np.all(s.velocity_sigma[:, ~border] > 0)
    assert sorted(os.listdir(figs)) == ["tracked_contours.png", "velocity_lpc.png"]


def test_observe_command_user_errors_exit_2(tmp_path, capsys):
    assert main(["observe", str(tmp_path / "nope.npz"), "--out", str(tmp_path / "o.npz")]) == 2
    p = tmp_path / "empty.npz"
    np.savez(p, masks=np.zeros((3, 20, 20), bool))
    assert main(["observe", str(p), "--out", str(tmp_path / "o.npz")]) == 2
    err = capsys.readouterr().err
    assert "masks[0]: expected some tissue" in err and "Traceback" not in err
