"""``sfem-filters strain``: a DENSE-Sim case folder in, the issue's JSON out (names, shapes, bands)."""
import json
from dataclasses import fields

import numpy as np
import pytest

from helpers import write_case_frames
from sfem_filters import datasets
from sfem_filters.cli import build_parser, main
from sfem_filters.cli.strain_input import _dense_settings, _strain_input

CASE = "dense_sim/phantom_subject_1"


@pytest.fixture(scope="module")
def short_case(tmp_path_factory):
    """The phantom case cut to its first 6 frames, written as a case folder is published."""
    return write_case_frames(datasets.dataset_path(CASE), tmp_path_factory.mktemp("case") / "phantom_short", 6)


@pytest.mark.needs_data(CASE)
def test_strain_writes_the_issue_json_with_bands_around_the_curves(short_case, tmp_path, capsys):
    out = tmp_path / "strain.json"
    assert main(["strain", str(short_case), "--json", str(out), "--snr", "30", "--segment-start", "30",
                 "--quiet"]) == 0
    d = json.loads(out.read_text())
    P = len(d["points"])
    F = len(d["frame_times_s"])
    assert F == 6 and P > 500 and d["route"] == "dense" and d["seconds"] > 0
    assert np.array(d["points"]).shape == (P, 2)
    for k in ("Ecc", "Err", "Ecr", "Ecc_sd", "Err_sd"):
        assert np.array(d["strain"][k], float).shape == (F, P), k
    assert np.nanmin(np.array(d["strain"]["Ecc_sd"], float)) >= 0
    for k in ("Ecc", "Err"):
        g = {s: np.array(d["global"][k + s], float) for s in ("", "_lo", "_hi")}
        assert g[""].shape == (F,) and np.all(g["_lo"] <= g[""]) and np.all(g[""] <= g["_hi"])
        seg = {s: np.array(d["segments"][k + s], float) for s in ("", "_lo", "_hi")}
        assert seg[""].shape == (6, F) and np.all(seg["_lo"] <= seg[""]) and np.all(seg[""] <= seg["_hi"])
    assert d["segments"]["start_deg"] == 30
    conv = d["conventional"]
    assert conv["segments"]["start_deg"] == 30 and conv["smoothing_sigma_px"] == 1.0
    assert np.array(conv["strain"]["Err"], float).shape == (F, P)
    # the radial strain thickens the wall in systole in both analyses (DENSE-Sim's phantom)
    assert np.array(d["global"]["Err"], float)[-1] > 0 and np.array(conv["global"]["Err"], float)[-1] > 0
    assert d["settings"]["noise_snr"] == 30
    printed = capsys.readouterr()
    assert "reference pixels x 6 frames" in printed.out and "progress" not in printed.err
    # the case has a ground truth: the summary line shows its global peaks beside ours
    t = d["truth"]["global"]
    assert (f"the case's ground truth: Ecc {100 * np.nanmin(np.array(t['Ecc'], float)):.2f}%, "
            f"Err {100 * np.nanmax(np.array(t['Err'], float)):.2f}%;") in printed.out
    # our peaks and their frames' times as the JSON has them, with the band of the curve there
    g, ms = d["global"], 1e3 * np.array(d["frame_times_s"], float)
    k = int(np.nanargmin(np.array(g["Ecc"], float)))
    assert (f"global peak Ecc {100 * g['Ecc'][k]:.2f}% at {ms[k]:.0f} ms (95% band of the curve at that frame, "
            "not of the peak: "
            f"{100 * g['Ecc_lo'][k]:.2f} to {100 * g['Ecc_hi'][k]:.2f}%)") in printed.out
    labels = np.array(d["labels"])
    assert labels.shape == (P,) and set(labels) <= set(range(6))
    e = np.array(d["strain"]["Ecc"], float)                   # labels say which pixels make each segment's curve
    for s in set(labels):
        np.testing.assert_allclose(np.array(d["segments"]["Ecc"][s], float), e[:, labels == s].mean(axis=1),
                                   rtol=1e-9, atol=1e-12)
    assert np.array(d["displacement"], float).shape == (F, P, 2)


@pytest.mark.needs_data(CASE)
def test_strain_runs_the_contours_route_from_the_masks_alone(short_case, tmp_path):
    """``--route contours``: the same JSON names, the route named, the spline through its landmarks beside."""
    out = tmp_path / "c.json"
    assert main(["strain", str(short_case), "--json", str(out), "--route", "contours", "--quiet"]) == 0
    d = json.loads(out.read_text())
    F, P = len(d["frame_times_s"]), len(d["points"])
    assert d["route"] == "contours" and F == 6
    assert np.array(d["strain"]["Ecc"], float).shape == (F, P)
    assert np.array(d["segments"]["Err_lo"], float).shape == (6, F)
    assert "landmarks" in d and "tracked contour landmarks" in d["spline"]["through"] and "conventional" in d


def test_strain_refuses_a_folder_that_is_not_a_case(tmp_path, capsys):
    assert main(["strain", str(tmp_path), "--json", str(tmp_path / "x.json")]) == 2
    assert "path: expected a DENSE-Sim case folder" in capsys.readouterr().err


def test_strain_argument_errors_say_what_was_expected(capsys):
    with pytest.raises(SystemExit):
        main(["strain", "x", "--json", "y", "--conventional-sigma", "-1"])
    assert "a number >= 0" in capsys.readouterr().err


# the DENSE route's default for images: the acquisition's point spread, each frame's mask fused, the profile

#: Each switch of the DENSE route's default and what it sets.
SWITCHES = {"stated": (["--phase-noise-level", "stated"], {"phase_noise_level": "stated", "border_masks": True}),
            "alone": (["--no-masks"], {"border_masks": False, "phase_noise_level": "stated",
                                       "mask_noise_level": "stated"}),
            "point": (["--resolution-px", "1"], {"resolution_px": 1.0, "border_masks": True}),
            "constant": (["--process-profile", "constant"], {"process_profile": "constant"}),
            "landmarks": (["--border-correspondence", "landmarks"], {"border_correspondence": "landmarks"}),
            "starts": (["--border-starts", "2"], {"border_correspondence": "landmarks", "border_starts": 2}),
            "mask_stated": (["--mask-noise-level", "stated"], {"mask_noise_level": "stated"})}
#: The switches run end to end in the default suite (each takes its own path through the route); all of
#: them run in the slow test.
RUN_BY_DEFAULT = ("alone", "landmarks")


def _run_switches(short_case, tmp_path, names):
    got = {}
    for name in names:
        path = tmp_path / f"{name}.json"
        assert main(["strain", str(short_case), "--json", str(path), "--snr", "30", "--quiet",
                     *SWITCHES[name][0]]) == 0
        got[name] = json.loads(path.read_text())
    return got


def _assert_each_changes_the_estimate(base, got):
    base = np.array(base["global"]["Err"], float)
    for name, rep in got.items():                    # each part changes the estimate: none is ignored
        assert np.max(np.abs(np.array(rep["global"]["Err"], float) - base)) > 1e-6, name


@pytest.mark.needs_data(CASE)
def test_default_for_images_fuses_the_masks_through_the_point_spread_and_each_part_can_be_turned_off(short_case,
                                                                                                     tmp_path):
    out = tmp_path / "default.json"
    assert main(["strain", str(short_case), "--json", str(out), "--snr", "30", "--quiet"]) == 0
    d = json.loads(out.read_text())
    s = d["settings"]
    assert d["route"] == "dense" and s["border_masks"] is True and s["phase_noise_level"] == "evidence"
    assert s["resolution_px"] == pytest.approx(128 / 60)               # config.yaml N_im / N_im_pre_spiral
    assert s["process_profile"] == "data"
    assert s["border_rows"] == s["border_nodes"] > 20 and s["border_correspondence"] == "phase"
    assert s["border_landmarks"] is None                                 # the phase places the border, no landmarks
    assert s["phase_noise_scale"] > 0 and s["phase_noise_scale"] != 1.0
    assert s["mask_noise_level"] == "evidence" and s["mask_noise_scale"] > 0 and s["mask_noise_scale"] != 1.0
    assert np.array(d["global"]["Err"], float).shape == (6,)
    assert np.all(np.isfinite(np.array(d["strain"]["Err"], float)))
    # every switch reaches the route's settings, the others left at the default's
    parser = build_parser()
    base = ["strain", str(short_case), "--json", str(tmp_path / "unused.json"), "--snr", "30"]
    src = _strain_input(parser.parse_args(base), lambda m: None)
    default = _dense_settings(parser.parse_args(base), src)
    assert default.border_masks and default.resolution_px == pytest.approx(128 / 60)
    for name, (extra, expected) in SWITCHES.items():
        switched = _dense_settings(parser.parse_args([*base, *extra]), src)
        changed = {f.name: getattr(switched, f.name) for f in fields(switched)
                   if getattr(switched, f.name) != getattr(default, f.name)}
        wanted = {k: v for k, v in expected.items() if getattr(default, k) != v}
        assert wanted and changed == wanted, name                 # each switch changes something, and only that
    # end to end, two switches that take their own path through the route
    got = _run_switches(short_case, tmp_path, RUN_BY_DEFAULT)
    alone = got["alone"]["settings"]
    assert alone["border_masks"] is False and alone["phase_noise_level"] == "stated" and "border_rows" not in alone
    lm = got["landmarks"]["settings"]
    assert lm["border_correspondence"] == "landmarks" and lm["border_landmarks"] > lm["border_nodes"]
    _assert_each_changes_the_estimate(d, got)


@pytest.mark.needs_data(CASE)
@pytest.mark.slow
def test_every_switch_of_the_default_changes_the_estimate(short_case, tmp_path):
    out = tmp_path / "default.json"
    assert main(["strain", str(short_case), "--json", str(out), "--snr", "30", "--quiet"]) == 0
    d = json.loads(out.read_text())
    s = d["settings"]
    got = _run_switches(short_case, tmp_path, SWITCHES)
    assert got["stated"]["settings"]["phase_noise_scale"] == 1.0
    assert got["stated"]["settings"]["border_rows"] == s["border_rows"]
    alone = got["alone"]["settings"]
    assert alone["border_masks"] is False and alone["phase_noise_level"] == "stated" and "border_rows" not in alone
    assert got["point"]["settings"]["resolution_px"] == 1.0 and got["point"]["settings"]["border_masks"] is True
    assert got["constant"]["settings"]["process_profile"] == "constant"
    for name in ("landmarks", "starts"):                     # --border-starts implies the landmarks it averages
        lm = got[name]["settings"]
        assert lm["border_correspondence"] == "landmarks" and lm["border_landmarks"] > lm["border_nodes"]
    assert got["starts"]["settings"]["border_starts"] == 2
    assert np.max(np.abs(np.array(got["starts"]["global"]["Err"], float)
                         - np.array(got["landmarks"]["global"]["Err"], float))) > 1e-6    # the starts count
    assert got["mask_stated"]["settings"]["mask_noise_scale"] == 1.0
    _assert_each_changes_the_estimate(d, got)


@pytest.mark.needs_data(CASE)
def test_mask_options_errors_name_the_argument(short_case, tmp_path, capsys):
    out = str(tmp_path / "x.json")
    assert main(["strain", str(short_case), "--json", out, "--with-masks", "--route", "contours"]) == 2
    assert "--with-masks/--no-masks: is for the dense route" in capsys.readouterr().err
    yy, xx = np.mgrid[0:20, 0:20]
    ring = (np.hypot(xx - 9.5, yy - 9.5) >= 4) & (np.hypot(xx - 9.5, yy - 9.5) <= 7)
    rows, cols = np.nonzero(ring)
    pts = np.column_stack([cols, rows]).astype(float)
    disp = 0.02 * np.arange(4)[:, None, None] * (pts - 9.5)[None]
    np.savez(tmp_path / "seq.npz", points=pts, displacement=disp, pixel_spacing=1.5e-3, frame_interval=0.02)
    assert main(["strain", str(tmp_path / "seq.npz"), "--json", out, "--with-masks", "--quiet"]) == 2
    assert "--with-masks: expected the myocardium mask of every frame, moving with the wall, got none" \
        in capsys.readouterr().err
    still = np.zeros((20, 20), bool)
    still[rows, cols] = True
    np.savez(tmp_path / "still.npz", points=pts, displacement=disp, pixel_spacing=1.5e-3, frame_interval=0.02,
             reference_mask=still, frame_masks=np.repeat(still[None], 4, axis=0))
    assert main(["strain", str(tmp_path / "still.npz"), "--json", out, "--with-masks", "--quiet"]) == 2
    assert "got masks that do not move (every frame's is the reference's)" in capsys.readouterr().err
    assert main(["strain", str(tmp_path / "seq.npz"), "--json", out, "--phase-noise-level", "evidence"]) == 2
    assert "--phase-noise-level: weighs the phase data against the masks, which this run does not fuse (no mask" \
        in capsys.readouterr().err
    assert main(["strain", str(short_case), "--json", out, "--no-masks", "--phase-noise-level", "evidence"]) == 2
    assert "which this run does not fuse (--no-masks)" in capsys.readouterr().err
    assert main(["strain", str(short_case), "--json", out, "--border-starts", "4", "--border-correspondence", "phase",
                 "--quiet"]) == 2
    assert "--border-starts: averages landmarks tracked from several contour starts; with --border-correspondence " \
           "phase there are none" in capsys.readouterr().err
    assert main(["strain", str(short_case), "--json", out, "--no-masks", "--mask-noise-level", "evidence"]) == 2
    assert "--mask-noise-level: weighs the masks against the phase data, which this run does not fuse (--no-masks)" \
        in capsys.readouterr().err
    assert main(["strain", str(short_case), "--json", out, "--no-masks", "--border-correspondence", "landmarks"]) == 2
    assert "--border-correspondence: places the masks' border data, which this run does not fuse (--no-masks)" \
        in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["strain", str(short_case), "--json", out, "--no-masks", "--with-masks"])
    assert "not allowed with argument" in capsys.readouterr().err


@pytest.mark.needs_data(CASE)
def test_the_contours_route_refuses_the_dense_routes_options(short_case, tmp_path, capsys):
    for extra in (["--process-profile", "data"], ["--resolution-px", "2"], ["--no-masks"],
                  ["--phase-noise-level", "stated"], ["--border-correspondence", "phase"],
                  ["--mask-noise-level", "stated"]):
        assert main(["strain", str(short_case), "--json", str(tmp_path / "c.json"), "--route", "contours",
                     *extra, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert extra[0] in err and "is for the dense route" in err, extra
