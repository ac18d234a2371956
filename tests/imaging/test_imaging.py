"""Image front end: contours, shape tracking (Eqs. 35-37), phase coherence (Eqs. 38-39),
segmentation and readers."""

import numpy as np
import pytest
from helpers import ring
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.imaging.confidence import (
    bending_energy,
    goodness_uniqueness,
    local_phase_coherence,
    match_confidence,
    weighted_std,
)
from sfem_filters.imaging.contours import (
    check_myocardium_mask,
    curvature,
    mask_borders,
    resample_closed,
    signed_area,
)
from sfem_filters.imaging.phase_contrast import sample_bilinear
from sfem_filters.imaging.readers import make_image_series, read_images
from sfem_filters.imaging.segmentation import dice, segment_sequence
from sfem_filters.imaging.tracking import (
    TrackingOptions,
    contour_curvature,
    smooth_vectors,
    track_masks,
)


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


def test_sample_bilinear_exact_on_linear_fields_and_checks_bounds():
    yy, xx = np.mgrid[0:10, 0:12]
    img = 2.0 * xx - 3.0 * yy + 1.0
    pts = np.array([[3.25, 4.5], [0.0, 0.0], [11.0, 9.0]])
    assert np.allclose(sample_bilinear(img, pts), 2 * pts[:, 0] - 3 * pts[:, 1] + 1)
    with pytest.raises(ValueError, match="points: expected positions inside"):
        sample_bilinear(img, [[12.5, 1.0]])


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
    pytest.importorskip("pydicom")
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
