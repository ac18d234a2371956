"""``sfem-filters strain`` reads a DENSE DICOM folder and a sequence ``.npz`` as well as a DENSE-Sim case folder.

The DICOM folder is the DENSE-Sim case written out as a scanner exports it (12-bit stored phase with
RescaleSlope and RescaleIntercept, TriggerTime per frame, PixelSpacing, the series told apart by
ImageComments); read back through ``strain``, its report must match the case folder's run within the
quantisation of the stored integers. The sequence is the case's Lagrangian tracks in the library's
point-tracking format, its points shuffled and without a mask, so the command must put them back
on the pixel grid.
"""
import json
import shutil

import numpy as np
import pydicom                                  # the test extra's (pyproject): the DICOM route is tested, not skipped
import pytest
import yaml
from scipy.ndimage import binary_erosion

from helpers import write_case_frames, write_dicom
from sfem_filters import datasets
from sfem_filters.cardiac import StrainRouteSettings, dense_strain
from sfem_filters.cli import main
from sfem_filters.imaging import (LagrangianDisplacement, conventional_from_displacement, mask_centre,
                                  phase_to_displacement, read_dense_dicom_folder, read_dense_sim)


CASE = "dense_sim/phantom_subject_1"
FRAMES = 5
STRIDE = 3                                     # frames 0, 3, ..., 12 of the case: 22.5 to 202.5 ms
KE = 0.1                                       # cycles/mm, DENSE-Sim's config.yaml
PX_MM = 1.75                                   # FOV 224 mm / 128
LEVELS = 4095                                  # 12-bit stored phase: 0..4095 over -pi..pi
PHASE_STEP = 2 * np.pi / LEVELS                # rad per stored integer
# the largest displacement error (pixels) the phase's rounding to stored integers makes:
# half a step of phase over 2 pi ke (rad per mm of displacement) times the pixel size
DU_PX = 0.5 * PHASE_STEP / (2 * np.pi * KE * PX_MM)


@pytest.fixture(scope="module")
def short_case(tmp_path_factory):
    """The phantom case at every STRIDE-th frame (FRAMES of them, into systole: strain of several percent),
    written as a case folder is published."""
    return write_case_frames(datasets.dataset_path(CASE), tmp_path_factory.mktemp("case") / "phantom_short",
                             FRAMES, STRIDE)


def _stored_phase(phase):
    """12-bit integers 0..4095 over -pi..pi (a scanner's phase image)."""
    return np.round((np.asarray(phase, float) + np.pi) / PHASE_STEP).astype(np.uint16)


def _write_export(folder, case_dir, with_comments=True):
    """The case as DICOM: phase with RescaleSlope 2, RescaleIntercept -4096 (rescaled -4096..4094 = -pi..pi),
    magnitude scaled to 12 bits; one flat folder of files in scrambled order, told apart by ImageComments
    (``with_comments``), else in the sub-folders phase_x, phase_y, magnitude."""
    folder.mkdir()
    phases = [np.load(case_dir / "phase_x.npy"), np.load(case_dir / "phase_y.npy")]
    mag = np.load(case_dir / "magnitude.npy").astype(float)
    with open(case_dir / "config.yaml") as f:
        sim = yaml.safe_load(f)["sim_params"]
    tt, n_acq = sim["tt"], int(sim["N_im_pre_spiral"])        # the acquired matrix, as a scanner's header says
    F = mag.shape[0]
    mag_slope = float(mag.max()) / LEVELS
    series = [(f"DENSE {e}-enc pha - Scale:1.000000 EncFreq:{KE:.2f}", "phase_" + e, _stored_phase(p), 2.0, -4096.0)
              for e, p in zip("xy", phases)]
    series.append(("DENSE overall mag", "magnitude", np.round(mag / mag_slope).astype(np.uint16), mag_slope, 0.0))
    rng = np.random.default_rng(1)
    names = iter(rng.permutation(3 * F))
    for comment, sub, stored, slope, intercept in series:
        where = folder if with_comments else folder / sub
        where.mkdir(exist_ok=True)
        for f in range(F):
            text = f"{comment} - Rep:0/1 Slc:0/1 Par:0/1 Phs:{f}/{F} RCswap:0 RCSflip:0/0/0"
            write_dicom(where / f"IM_{next(names):04d}", stored[f], tt[f + 1], f + 1, slope, intercept,
                         comments=text if with_comments else None, acquisition_matrix=(0, n_acq, n_acq, 0))
    (folder / "DICOMDIR.txt").write_text("not a DICOM file")
    return folder, mag_slope


@pytest.fixture(scope="module")
def export(short_case, tmp_path_factory):
    base = tmp_path_factory.mktemp("dicom")
    folder, mag_slope = _write_export(base / "export", short_case)
    masks = base / "masks.npy"
    np.save(masks, np.load(short_case / "LV_mask_time_lowres.npy"))
    return {"folder": folder, "masks": masks, "mag_slope": mag_slope, "base": base}


@pytest.fixture(scope="module")
def folder_report(short_case, tmp_path_factory):
    """The case folder's strain report (the reference both other inputs are held to)."""
    out = tmp_path_factory.mktemp("ref") / "folder.json"
    assert main(["strain", str(short_case), "--json", str(out), "--quiet"]) == 0
    return json.loads(out.read_text())


def _a(x):
    return np.array(x, float)


# ------------------------------------------------------------------------------------------ DICOM
@pytest.mark.needs_data(CASE)
def test_the_dicom_reader_gives_the_case_within_the_stored_integers(short_case, export):
    ref = read_dense_sim(short_case)
    got = read_dense_dicom_folder(export["folder"], np.load(export["masks"]), KE, phase_range=(-4096, 4094))
    wrapped = np.angle(np.exp(1j * (got.phases - ref.phases)))           # -pi and pi are the same phase
    assert np.abs(wrapped).max() <= 0.5 * PHASE_STEP + 1e-6
    assert np.abs(got.magnitude - ref.magnitude).max() <= 0.5 * export["mag_slope"] * (1 + 1e-6)
    assert np.array_equal(got.masks, ref.masks)
    assert got.frame_times_s == pytest.approx(ref.frame_times_s, abs=1e-12)
    assert got.pixel_size_m == pytest.approx(ref.pixel_size_m) and got.ke_per_m == pytest.approx(ref.ke_per_m)


@pytest.mark.needs_data(CASE)
def test_the_sub_folder_layout_in_radians_with_per_frame_masks(short_case, tmp_path):
    """No ImageComments: the series are the sub-folders; a rescale straight to radians needs no phase range;
    (F, H, W) masks take frame 0's as the reference."""
    ref = read_dense_sim(short_case)
    folder = tmp_path / "plain"
    folder.mkdir()
    for j, sub in enumerate(("phase_x", "phase_y")):
        (folder / sub).mkdir()
        for f in range(FRAMES):
            write_dicom(folder / sub / f"{f}.dcm", _stored_phase(ref.phases[j, f]), 1e3 * ref.frame_times_s[f], f + 1,
                         slope=PHASE_STEP, intercept=-np.pi)
    (folder / "magnitude").mkdir()
    for f in range(FRAMES):
        write_dicom(folder / "magnitude" / f"{f}.dcm", np.full(ref.shape, 1000), 1e3 * ref.frame_times_s[f], f + 1,
                     slope=1.0, intercept=0.0)
    got = read_dense_dicom_folder(folder, ref.frame_masks, KE)
    assert np.abs(np.angle(np.exp(1j * (got.phases - ref.phases)))).max() <= 0.5 * PHASE_STEP + 1e-6
    assert np.array_equal(got.reference_mask, ref.masks[1]) and np.array_equal(got.frame_masks, ref.frame_masks)
    with pytest.warns(UserWarning, match="used as the reference and as every frame's"):
        one = read_dense_dicom_folder(folder, ref.reference_mask, KE)
    assert all(np.array_equal(m, ref.reference_mask) for m in one.masks)


@pytest.mark.slow
@pytest.mark.needs_data(CASE)
def test_strain_of_the_dicom_export_equals_the_case_folders_within_the_quantisation(export, folder_report, tmp_path):
    out = tmp_path / "dicom.json"
    assert main(["strain", str(export["folder"]), "--json", str(out), "--ke", str(KE), "--masks", str(export["masks"]),
                 "--phase-range", "-4096", "4094", "--quiet"]) == 0
    d, ref = json.loads(out.read_text()), folder_report
    assert d["settings"]["input"]["kind"] == "DENSE DICOM folder" and d["route"] == ref["route"]
    assert np.array_equal(_a(d["points"]), _a(ref["points"]))
    assert _a(d["frame_times_s"]) == pytest.approx(_a(ref["frame_times_s"]), abs=1e-12)
    # the conventional analysis differences the tracks: a displacement error of DU_PX at each of two pixels
    # (one-sided differences at the borders) moves a gradient entry by at most 2 DU_PX; the Lagrangian inversion
    # and the Green strain's quadratic term at most double it
    conv, conv_ref = d["conventional"]["strain"], ref["conventional"]["strain"]
    for k in ("Ecc", "Err", "Ecr"):
        assert np.nanmax(np.abs(_a(conv[k]) - _a(conv_ref[k]))) <= 4 * DU_PX, k
    # ours: the same data up to that error through the same smoother, whose strain at a pixel averages the data's
    # differences over an element or more (at most 2 DU_PX); a curve averages a segment's ~160 pixels, whose
    # rounding errors are independent, so it keeps a small part of one pixel's (0.5 DU_PX). Run once with
    # --ke 0.105 (5% off), the differences were 5-25 DU_PX (pixels) and 0.6-7 DU_PX (curves) on this case
    for k in ("Ecc", "Err", "Ecr"):
        assert np.nanmax(np.abs(_a(d["strain"][k]) - _a(ref["strain"][k]))) <= 2 * DU_PX, k
    for k in ("Ecc", "Err", "Ecc_lo", "Ecc_hi", "Err_lo", "Err_hi"):
        assert np.abs(_a(d["global"][k]) - _a(ref["global"][k])).max() <= 0.5 * DU_PX, k
        assert np.abs(_a(d["segments"][k]) - _a(ref["segments"][k])).max() <= 0.5 * DU_PX, k
    assert "truth" in ref and "truth" not in d                      # DICOM carries no ground truth


# --------------------------------------------------------------------------------------- sequence
def _sequence_from(case_dir, path, rng, **drop):
    """The case's Lagrangian tracks as a sequence file: points shuffled, no mask, sigma the RMS of the
    components' sd, frame times and pixel size."""
    case = read_dense_sim(case_dir)
    tracks = phase_to_displacement(case)
    order = rng.permutation(len(tracks.points))
    sigma = np.sqrt(np.mean(tracks.sd ** 2, axis=2))
    sigma = np.where(np.isfinite(sigma), sigma, 1.0)             # the format wants finite sigma; NaN tracks
    payload = dict(points=tracks.points[order], displacement=tracks.displacement[:, order], sigma=sigma[:, order],
                   frame_interval=float(np.diff(case.frame_times_s)[0]), frame_times_s=case.frame_times_s,
                   pixel_spacing=case.pixel_size_m, provenance="DENSE-Sim phantom tracks")
    for key in drop:
        payload.pop(key)
    np.savez(path, **payload)
    return case, tracks, sigma


def _both(sigma, tracks):
    """The file's sigma on both components of every tracked datum, NaN where the track is missing."""
    tracked = np.isfinite(tracks.displacement).all(axis=2)
    return np.repeat(np.where(tracked, sigma, np.nan)[..., None], 2, axis=2)


@pytest.mark.slow
@pytest.mark.needs_data(CASE)
def test_strain_of_the_tracks_as_a_sequence_is_the_route_on_those_tracks(short_case, folder_report, tmp_path):
    seq_path = tmp_path / "tracks.npz"
    case, tracks, sigma = _sequence_from(short_case, seq_path, np.random.default_rng(3))
    out = tmp_path / "seq.json"
    assert main(["strain", str(seq_path), "--json", str(out), "--quiet"]) == 0
    d = json.loads(out.read_text())
    assert d["settings"]["input"]["kind"] == "sequence file" and d["settings"]["input"]["points_reordered"]
    assert np.array_equal(_a(d["points"]), tracks.points)                       # back in row-major order
    assert _a(d["frame_times_s"]) == pytest.approx(case.frame_times_s, abs=0)
    # the conventional analysis is the tracks' finite differences: the case folder's, exactly
    for k in ("Ecc", "Err", "Ecr"):
        assert np.allclose(_a(d["conventional"]["strain"][k]), _a(folder_report["conventional"]["strain"][k]),
                           atol=1e-12, equal_nan=True), k
    assert "finite-difference" in d["conventional"]["what"] and "sequence" in d["conventional"]["what"]
    # ours: the DENSE route on the same tracks with the file's sd on both components
    same = LagrangianDisplacement(points=tracks.points, displacement=tracks.displacement, sd=_both(sigma, tracks),
                                  confidence=np.ones(sigma.shape),
                                  frame_times_s=case.frame_times_s, n_untracked=tracks.n_untracked,
                                  noise_sd=np.full(2, np.nan))
    want = dense_strain(same, case.reference_mask, case.pixel_size_m, StrainRouteSettings()).to_dict()
    for k in ("Ecc", "Err", "Ecr", "Ecc_sd", "Err_sd"):
        assert np.allclose(_a(d["strain"][k]), _a(want["strain"][k]), rtol=1e-6, atol=1e-9), k
    for k in ("Ecc", "Err", "Ecc_lo", "Err_hi"):
        assert np.allclose(_a(d["segments"][k]), _a(want["segments"][k]), rtol=1e-6, atol=1e-9), k


@pytest.mark.needs_data(CASE)
def test_the_sequence_tracks_reach_the_route_as_the_case_folders(short_case, tmp_path):
    """Quick: the tracks a sequence file hands the routes are the phase's tracks, points back in row-major order,
    the reference mask the case's; their finite differences are the case folder's conventional analysis."""
    from sfem_filters.cli import build_parser
    from sfem_filters.cli.strain_input import _sequence_input
    seq_path = tmp_path / "tracks.npz"
    case, tracks, sigma = _sequence_from(short_case, seq_path, np.random.default_rng(4))
    args = build_parser().parse_args(["strain", str(seq_path), "--json", str(tmp_path / "x.json")])
    src = _sequence_input(args, lambda m: None)
    assert np.array_equal(src["tracks"].points, tracks.points)
    assert np.array_equal(src["tracks"].displacement, tracks.displacement, equal_nan=True)
    assert np.allclose(src["tracks"].sd, _both(sigma, tracks), equal_nan=True)
    h, w = src["reference_mask"].shape                          # the points' pixels, two background pixels beyond
    assert np.array_equal(src["reference_mask"], case.reference_mask[:h, :w])
    assert src["reference_mask"].sum() == case.reference_mask.sum()
    assert src["pixel_size_m"] == case.pixel_size_m and src["masks"] is None
    c = mask_centre(case.reference_mask)
    got = conventional_from_displacement(src["tracks"], c)
    ref = conventional_from_displacement(tracks, c)
    assert np.allclose(got.strain.Err, ref.strain.Err, equal_nan=True, atol=1e-12)


# ------------------------------------------------------------------------------------- bad input
def _err(capsys, argv):
    assert main(argv) == 2
    return capsys.readouterr().err


@pytest.mark.needs_data(CASE)
def test_dicom_input_errors_name_the_argument(export, short_case, tmp_path, capsys):
    folder, masks = str(export["folder"]), str(export["masks"])
    out = str(tmp_path / "x.json")
    base = ["strain", folder, "--json", out]
    good = ["--ke", str(KE), "--masks", masks, "--phase-range", "-4096", "4094"]
    assert "--ke: expected the DENSE encoding frequency in cycles/mm" in _err(capsys, base + good[2:])
    assert "--masks: expected a .npy file" in _err(capsys, base + good[:2] + good[4:])
    assert "no such file" in _err(capsys, base + ["--ke", "0.1", "--masks", str(tmp_path / "absent.npy")])
    m = np.load(masks)
    for name, bad, message in [
            ("frames", m[:3], "--masks: expected (H, W) the reference, (F, H, W) each frame's or (F + 1, H, W)"),
            ("size", m[:, :64], "--masks: expected masks of the images' size 128 x 128"),
            ("empty_ref", np.concatenate([np.zeros_like(m[:1]), m[1:]]), "--masks: expected the reference mask"),
            ("empty_frame", np.concatenate([m[:2], np.zeros_like(m[2:3]), m[3:]]),
             r"--masks: expected myocardium in every frame's mask, got none in frame(s) [1]"),
            ("empty_2d", np.zeros(m.shape[1:], bool), "--masks: expected a mask holding some tissue"),
            ("float", m * 0.5, "--masks: expected a boolean mask")]:
        np.save(tmp_path / f"{name}.npy", bad)
        err = _err(capsys, base + good[:2] + ["--masks", str(tmp_path / f"{name}.npy")] + good[4:])
        assert message in err, (name, err)
    err = _err(capsys, base + good[:4])                                           # no --phase-range
    assert "expected phases in radians within +-pi" in err and "give --phase-range" in err
    err = _err(capsys, base + good[:4] + ["--phase-range", "-2048", "2047"])
    assert "expected rescaled values within --phase-range -2048 to 2047" in err
    assert "--phase-range: expected lo < hi" in _err(capsys, base + good[:4] + ["--phase-range", "1", "-1"])
    err = _err(capsys, base + good + ["--directions", "1", "0", "1", "0"])
    assert "--directions: expected two independent unit vectors" in err
    # a DENSE-Sim case folder carries its own ke and masks
    assert "--ke: is for DICOM folders" in _err(capsys, ["strain", str(short_case), "--json", out, "--ke", "0.1"])


@pytest.mark.needs_data(CASE)
def test_dicom_folder_errors_name_the_series(export, tmp_path, capsys):
    good = ["--ke", str(KE), "--masks", str(export["masks"]), "--phase-range", "-4096", "4094"]
    out = str(tmp_path / "x.json")
    missing = tmp_path / "no_y"
    shutil.copytree(export["folder"], missing)
    for p in missing.iterdir():
        if p.name.startswith("IM_") and "y-enc pha" in str(pydicom.dcmread(p).ImageComments):
            p.unlink()
    err = _err(capsys, ["strain", str(missing), "--json", out] + good)
    assert "path: expected the DENSE series pha.x, pha.y and a magnitude" in err and "missing ['pha.y']" in err
    small = tmp_path / "small"
    shutil.copytree(export["folder"], small)
    for p in small.iterdir():                             # the x phase written at half size
        if p.name.startswith("IM_"):
            ds = pydicom.dcmread(p)
            if "x-enc pha" in str(ds.ImageComments):
                write_dicom(p, ds.pixel_array[::2, ::2], ds.TriggerTime, ds.InstanceNumber, 2.0, -4096.0,
                             comments=ds.ImageComments)
    err = _err(capsys, ["strain", str(small), "--json", out] + good)
    assert "path (DENSE x-enc pha series): expected the magnitude's shape" in err
    late = tmp_path / "late"
    shutil.copytree(export["folder"], late)
    for p in late.iterdir():                              # the y phase's frames 5 ms after the magnitude's
        if p.name.startswith("IM_"):
            ds = pydicom.dcmread(p)
            if "y-enc pha" in str(ds.ImageComments):
                ds.TriggerTime = float(ds.TriggerTime) + 5.0
                ds.save_as(p)
    err = _err(capsys, ["strain", str(late), "--json", out] + good)
    assert "path (DENSE y-enc pha series): expected the magnitude's TriggerTime of each frame (ms)" in err
    twice = tmp_path / "twice"
    shutil.copytree(export["folder"], twice)
    first = next(p for p in sorted(twice.iterdir()) if p.name.startswith("IM_")
                 and "overall mag" in str(pydicom.dcmread(p).ImageComments))
    shutil.copy(first, twice / "copy_of_a_frame")           # two files at one trigger time: two slices
    err = _err(capsys, ["strain", str(twice), "--json", out] + good)
    assert "path (DENSE overall mag series): expected one file per frame (one slice, one repetition)" in err
    plain = tmp_path / "plain"
    plain.mkdir()
    write_dicom(plain / "a.dcm", np.zeros((8, 8)), 20.0, 1, 1.0, 0.0)
    err = _err(capsys, ["strain", str(plain), "--json", out] + good)
    assert "path: expected DENSE DICOM files told apart by ImageComments" in err and "phase_x, phase_y" in err


def test_a_ke_that_differs_from_the_files_encfreq_is_warned_about(tmp_path):
    """The argument wins; the ImageComments' EncFreq only checks it."""
    yy, xx = np.mgrid[0:24, 0:24]
    ring = (np.hypot(xx - 11.5, yy - 11.5) >= 4) & (np.hypot(xx - 11.5, yy - 11.5) <= 9)
    folder = tmp_path / "f"
    folder.mkdir()
    for f in range(3):
        for e in "xy":
            write_dicom(folder / f"{e}{f}", np.full((24, 24), 2048), 20 + 15 * f, f + 1, 2.0, -4096.0,
                         comments=f"DENSE {e}-enc pha - Scale:1.000000 EncFreq:0.08 Phs:{f}/3")
        write_dicom(folder / f"m{f}", np.full((24, 24), 100), 20 + 15 * f, f + 1, 1.0, 0.0,
                     comments=f"DENSE overall mag - Phs:{f}/3")
    with pytest.warns(UserWarning, match="EncFreq 0.08; the given value is used"):
        case = read_dense_dicom_folder(folder, np.stack([ring] * 4), 0.1, phase_range=(-4096, 4094))
    assert case.ke_per_m == pytest.approx(100.0) and case.frame_times_s == pytest.approx([0.02, 0.035, 0.05])
    assert np.abs(case.phases).max() < 2 * PHASE_STEP                  # 2048 of 0..4095 is phase 0


def test_sequence_input_errors_name_what_is_missing(tmp_path, capsys):
    yy, xx = np.mgrid[0:20, 0:20]
    ring = (np.hypot(xx - 9.5, yy - 9.5) >= 4) & (np.hypot(xx - 9.5, yy - 9.5) <= 7)
    rows, cols = np.nonzero(ring)
    pts = np.column_stack([cols, rows]).astype(float)
    disp = 0.02 * np.arange(4)[:, None, None] * (pts - 9.5)[None]           # a dilation, 4 frames
    full = dict(points=pts, displacement=disp, pixel_spacing=1.5e-3, frame_interval=0.02)
    out = str(tmp_path / "x.json")

    def run(name, extra=(), **change):
        payload = {**full, **change}
        payload = {k: v for k, v in payload.items() if v is not None}
        np.savez(tmp_path / f"{name}.npz", **payload)
        return _err(capsys, ["strain", str(tmp_path / f"{name}.npz"), "--json", out, *extra])

    assert "missing pixel_spacing (m)" in run("no_px", pixel_spacing=None)
    assert "missing frame_interval (s) (or frame_times_s" in run("no_dt", frame_interval=None)
    assert "frame_times_s: expected 4 frame times" in run("bad_t", frame_times_s=np.arange(3.0))
    assert "points: expected pixel centres" in run("off_grid", points=pts + 0.3)
    assert "points: expected distinct pixels" in run("dup", points=np.concatenate([pts[:-1], pts[:1]]))
    bigger = ring | np.roll(ring, 1, axis=1)
    assert "reference_mask: expected its tissue pixels to be exactly the points" in run("mask", reference_mask=bigger)
    assert "units: expected 'px'" in run("metres", units="m", pixel_spacing=None, points=pts * 1.5e-3,
                                         displacement=disp * 1.5e-3)
    assert "--ke: is for DENSE images" in run("ke", extra=("--ke", "0.1"))
    assert "--snr: is for DENSE images" in run("snr", extra=("--snr", "30"))
    assert "--route contours: expected the myocardium masks" in run("contours", extra=("--route", "contours"))
    assert "--border-starts: averages the masks' border data, which this run does not fuse (no mask of every " \
           "frame that moves)" in run("starts", extra=("--border-starts", "4"))
    with pytest.raises(SystemExit) as stop:
        main(["strain", str(tmp_path / "no_px.npz"), "--json", out, "--border-starts", "0"])
    assert stop.value.code == 2 and "expected an integer >= 1 contour start angles" in capsys.readouterr().err
    assert "--resolution-px acquisition: a sequence file carries no acquisition" in run(
        "res_seq", extra=("--resolution-px", "acquisition"))
    for bad in ("0.5", "nan", "wide"):                   # argparse's own error: usage and exit status 2
        with pytest.raises(SystemExit) as stop:
            main(["strain", str(tmp_path / "no_px.npz"), "--json", out, "--resolution-px", bad])
        err = capsys.readouterr().err
        assert stop.value.code == 2
        assert "argument --resolution-px: expected the acquired resolution in reconstructed pixels" in err
    err = _err(capsys, ["strain", str(tmp_path / "absent.npz"), "--json", out])
    assert "path: expected a DENSE-Sim case folder, a folder of DENSE DICOM files or a sequence .npz" in err


@pytest.mark.needs_data(CASE)
def test_the_acquisitions_resolution_reaches_the_route(short_case, folder_report, tmp_path):
    settings = folder_report["settings"]                                     # the default for images
    assert settings["resolution_px"] == pytest.approx(128 / 60)             # config.yaml N_im / N_im_pre_spiral
    assert settings["observation_tissue_weight_mean"] < 0.95                # border pixels' PSF reaches outside
    out = tmp_path / "point.json"
    assert main(["strain", str(short_case), "--json", str(out), "--quiet", "--resolution-px", "1"]) == 0
    rep = json.loads(out.read_text())
    assert rep["settings"]["resolution_px"] == 1.0                          # point observation
    # the operator changes the estimate (it is not ignored), within the strain's own scale
    a, b = _a(rep["global"]["Err"]), _a(folder_report["global"]["Err"])
    assert 1e-4 < np.max(np.abs(a - b)) < 0.2


# ------------------------------------------------------------------------------------------ masks with defects
def _with_masks(short_case, tmp_path, edit):
    dst = tmp_path / "case"
    shutil.copytree(short_case, dst)
    masks = np.load(dst / "LV_mask_time_lowres.npy")
    edit(masks)
    np.save(dst / "LV_mask_time_lowres.npy", masks)
    return dst, masks


def test_masks_with_small_defects_are_mended_and_a_broken_frame_leaves_its_own_border_data_out(short_case,
                                                                                                 folder_report,
                                                                                                 tmp_path, capsys):
    """Cases we are not given may carry coarse masks: a pinhole or a stray pixel is mended (with a warning) and
    the run goes on as before; a frame whose mask is no ring at all observes the phase alone (its border data left
    out, the other frames' fused); when no frame's mask is a ring the default uses the phase alone."""
    def small(m):
        r, c = np.argwhere(binary_erosion(m[2]))[0]
        m[2, r, c] = False                                  # a pinhole in one frame's wall
        m[0, 0, 0] = True                                   # a stray pixel in the reference mask
    folder, masks = _with_masks(short_case, tmp_path, small)
    out = tmp_path / "small.json"
    with pytest.warns(RuntimeWarning) as rec:
        assert main(["strain", str(folder), "--json", str(out), "--quiet"]) == 0
    said = " ".join(str(w.message) for w in rec)
    assert "reference_mask: not one ring" in said and "removed 1 stray piece(s) of 1 px" in said   # the mesh's mask
    assert "masks[2]" in said and "filled 1 hole(s) of 1 px" in said
    report = json.loads(out.read_text())
    assert report["settings"]["border_masks"] is True
    assert len(report["points"]) == int(masks[0].sum()) == len(folder_report["points"]) + 1   # every pixel scored
    assert np.all(np.isfinite(_a(report["strain"]["Ecc"])))

    def broken(m):
        m[3] = m[3] & (np.arange(m.shape[-1])[None, :] < m.shape[-1] // 2)    # half a ring: no cavity
    folder, _ = _with_masks(short_case, tmp_path / "b", broken)
    out = tmp_path / "broken.json"
    with pytest.warns(RuntimeWarning, match=r"frame\(s\) \[2\] \(masks\[3\]\) cannot be made one ring.*left out"):
        assert main(["strain", str(folder), "--json", str(out), "--quiet"]) == 0
    report = json.loads(out.read_text())
    assert report["settings"]["border_masks"] is True and np.all(np.isfinite(_a(report["strain"]["Err"])))

    def all_broken(m):
        m[1:] = m[1:] & (np.arange(m.shape[-1])[None, None, :] < m.shape[-1] // 2)
    folder, _ = _with_masks(short_case, tmp_path / "a", all_broken)
    with pytest.warns(RuntimeWarning, match=r"index \[1, 2, .*no frame's is left.*does without the masks"):
        assert main(["strain", str(folder), "--json", str(out), "--quiet"]) == 0
    assert json.loads(out.read_text())["settings"]["border_masks"] is False
    # asked for explicitly, the masks' defect is an error naming the masks
    capsys.readouterr()
    assert main(["strain", str(folder), "--json", str(out), "--quiet", "--with-masks"]) == 2
    err = capsys.readouterr().err
    assert "masks: expected at least one frame's mask" in err and "Traceback" not in err


def test_a_case_folder_missing_a_file_is_told_which(tmp_path, capsys):
    folder = tmp_path / "case"
    folder.mkdir()
    for name in ("phase_x.npy", "phase_y.npy", "magnitude.npy", "LV_mask_time_lowres.npy"):
        np.save(folder / name, np.zeros((2, 4, 4), np.float32))
    err = _err(capsys, ["strain", str(folder), "--json", str(tmp_path / "x.json")])
    assert "(a DENSE-Sim case folder? it has phase_x.npy, phase_y.npy, magnitude.npy, LV_mask_time_lowres.npy but " \
           "not config.yaml)" in err
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "(none of a DENSE-Sim case's files and no DICOM file)" in _err(
        capsys, ["strain", str(empty), "--json", str(tmp_path / "x.json")])


def test_the_segment_start_is_taken_modulo_360():
    from sfem_filters.cli._common import _angle_deg
    import argparse
    assert _angle_deg("400") == 40.0 and _angle_deg("-30") == 330.0 and _angle_deg("0") == 0.0
    assert _angle_deg("360") == 0.0 and _angle_deg("719.5") == 359.5
    for bad in ("nan", "inf", "north"):
        with pytest.raises(argparse.ArgumentTypeError, match="a finite number"):
            _angle_deg(bad)


def test_without_gmsh_the_command_says_how_to_install_it_before_reading_anything(tmp_path, capsys, monkeypatch):
    """Both routes mesh with Gmsh, an optional dependency: without it the command stops at once (exit 2, nothing
    read or written) and names the package and the project's extra."""
    import importlib.util
    from sfem_filters.cli import strain as strain_cli
    real = importlib.util.find_spec
    monkeypatch.setattr(strain_cli.importlib.util, "find_spec",
                        lambda name, *a: None if name == "gmsh" else real(name, *a))
    for route in ("dense", "contours"):
        out = tmp_path / f"{route}.json"
        assert main(["strain", str(tmp_path / "no_such_case"), "--json", str(out), "--route", route]) == 2
        err = capsys.readouterr().err
        assert "Gmsh" in err and "pip install 'gmsh>=4.11'" in err and "'.[mesh]'" in err and not out.exists()
