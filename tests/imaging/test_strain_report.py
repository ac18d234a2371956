"""A strain report's peaks, ground-truth block and tidy CSV (issue 42, item 4)."""
from __future__ import annotations

import csv
import gzip
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp
from strain_report_helpers import synthetic_report

from sfem_filters.imaging.strain import N_SEGMENTS, segment_labels
from sfem_filters.imaging.strain_report import (CSV_COLUMNS, Z95, csv_row_count, method_blocks, peaks, strain_csv,
                                                truth_block, with_peaks)


# ----------------------------------------------------------------------------------- peaks
@st.composite
def curve_with_a_known_extreme(draw):
    """A curve (F frames) with its extreme ``m`` placed at frame ``i``, every other value at least ``gap`` away,
    some other frames missing (NaN), and increasing frame times."""
    F = draw(st.integers(2, 40))
    i = draw(st.integers(0, F - 1))
    m = draw(st.floats(-0.5, 0.5))
    gap = draw(st.floats(1e-6, 0.1))
    rest = draw(hnp.arrays(float, F, elements=st.floats(0.0, 0.5)))
    missing = draw(hnp.arrays(bool, F))
    missing[i] = False
    curve = np.where(missing, np.nan, m + gap + rest)
    curve[i] = m
    times = np.cumsum(draw(hnp.arrays(float, F, elements=st.floats(1e-3, 0.1))))
    return curve, times, i, m


@settings(max_examples=80, deadline=None)
@given(curve_with_a_known_extreme())
def test_peak_of_ecc_is_its_minimum_and_of_err_its_maximum(case):
    curve, times, i, m = case
    p = peaks({"Ecc": curve, "Err": -curve}, times)
    assert p["Ecc"]["value"] == m and p["Ecc"]["frame"] == i and p["Ecc"]["time_s"] == times[i]
    assert p["Err"]["value"] == -m and p["Err"]["frame"] == i and p["Err"]["time_s"] == times[i]
    assert p["Ecc"]["lo"] is None and p["Ecc"]["hi"] is None               # no band given


@settings(max_examples=30, deadline=None)
@given(curve_with_a_known_extreme(), st.integers(1, 4))
def test_segment_peaks_are_those_of_each_row_with_the_band_at_the_peak_frame(case, shift):
    curve, times, i, m = case
    rows = np.stack([curve + k for k in range(3)])                          # (3, F): the same frame, shifted
    band = {"Ecc": rows, "Ecc_lo": rows - shift, "Ecc_hi": rows + shift}
    p = peaks(band, times)["Ecc"]
    assert p["frame"] == [i] * 3 and p["time_s"] == [times[i]] * 3
    np.testing.assert_allclose(p["value"], [m, m + 1, m + 2])
    np.testing.assert_allclose(p["lo"], np.array(p["value"]) - shift)
    np.testing.assert_allclose(p["hi"], np.array(p["value"]) + shift)


def test_peak_of_a_sampled_parabola_is_at_the_sample_nearest_its_vertex():
    t = np.linspace(0.0, 0.6, 41)
    vertex = 0.4123
    p = peaks({"Ecc": -0.2 + (t - vertex) ** 2, "Err": 0.5 - 3 * (t - vertex) ** 2}, t)
    nearest = int(np.argmin(np.abs(t - vertex)))
    assert p["Ecc"]["frame"] == p["Err"]["frame"] == nearest
    assert abs(p["Ecc"]["value"] + 0.2) <= (t[1] - t[0]) ** 2 / 4 + 1e-15


def test_a_curve_with_no_value_has_no_peak():
    p = peaks({"Ecc": [None, None, None]}, [0.1, 0.2, 0.3])
    assert p["Ecc"] == {"value": None, "time_s": None, "frame": -1, "lo": None, "hi": None}


@pytest.mark.parametrize("curves, times, expected", [
    ({"Ecc": [0.1, 0.2]}, [0.1, 0.2, 0.3], "curves['Ecc']: expected shape (3,) or (K, 3)"),
    ({"Err": [[[0.1]]]}, [0.1], "curves['Err']: expected shape (1,) or (K, 1)"),
    ({"Ecc": [0.1, 0.2], "Ecc_lo": [0.1]}, [0.1, 0.2], "curves['Ecc_lo']: expected shape (2)"),
    ({"Ecc": [0.1]}, [[0.1]], "times: expected shape (any)"),
])
def test_peaks_refuse_mismatched_shapes_naming_the_argument(curves, times, expected):
    with pytest.raises(ValueError, match=expected.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
        peaks(curves, times)


def test_with_peaks_adds_peaks_to_every_block_and_leaves_the_input_alone():
    r = synthetic_report()
    before = json.dumps(r)
    out = with_peaks(r)
    assert json.dumps(r) == before
    assert [name for name, _ in method_blocks(out)] == ["dense", "conventional", "spline", "truth"]
    for _, b in method_blocks(out):
        seg = np.array(b["segments"]["Ecc"], float)
        assert b["peaks"]["segments"]["Ecc"]["value"] == list(np.min(seg, axis=1))
        assert b["peaks"]["global"]["Err"]["value"] == max(b["global"]["Err"])
    assert out["peaks"]["global"]["Ecc"]["lo"] is not None and out["truth"]["peaks"]["global"]["Ecc"]["lo"] is None
    json.dumps(out)                                                           # still JSON


def test_method_blocks_refuse_what_is_not_a_report():
    with pytest.raises(ValueError, match="report: expected the strain report dict"):
        method_blocks({"points": []})


# ----------------------------------------------------------------------------------- truth
def test_truth_curves_are_means_over_the_same_segments():
    r = synthetic_report()
    X = np.array(r["points"])
    rng = np.random.default_rng(3)
    te, tr = rng.normal(size=(2, 5, len(X)))
    te[0, :4] = np.nan                                                        # a truth missing at some pixels
    b = truth_block(te, tr, X, r["centre"], 30.0, source="test")
    lab = segment_labels(X, r["centre"], 30.0)
    for k in range(N_SEGMENTS):
        want = np.nanmean(te[:, lab == k], axis=1)
        np.testing.assert_allclose(np.array(b["segments"]["Ecc"][k], float), want)
    np.testing.assert_allclose(np.array(b["global"]["Err"], float), tr.mean(axis=1))
    assert b["segments"]["start_deg"] == 30.0 and b["source"] == "test" and b["strain"]["Ecc"][0][0] is None


def test_truth_block_refuses_a_truth_of_another_size():
    with pytest.raises(ValueError, match="truth_ecc: expected shape"):
        truth_block(np.zeros((3, 4)), np.zeros((3, 4)), np.zeros((5, 2)), [0, 0])


# ----------------------------------------------------------------------------------- CSV
def _read(path):
    opener = gzip.open if str(path).endswith(".gz") else open
    with opener(path, "rt", newline="") as fh:
        return list(csv.DictReader(fh))


def _num(cell):
    return None if cell == "" else float(cell)


@pytest.mark.parametrize("name, empty", [("strain.csv", None), ("strain.csv.gz", 2)])
def test_csv_round_trips_with_a_row_per_method_region_frame_and_component(tmp_path, name, empty):
    r = synthetic_report(empty_segment=empty)
    path = strain_csv(r, tmp_path / name)
    rows = _read(path)
    F, P = len(r["frame_times_s"]), len(r["points"])
    # methods x regions x frames x components, each block with what it holds:
    # dense: pixels Ecc Err Ecr, curves Ecc Err; conventional: pixels Ecc Err Ecr; spline, truth: pixels Ecc Err
    pixel_rows = F * P * (3 + 3 + 2 + 2)
    curve_rows = 4 * F * (1 + N_SEGMENTS) * 2
    assert len(rows) == pixel_rows + curve_rows == csv_row_count(r)
    assert tuple(rows[0]) == CSV_COLUMNS
    blocks = dict(method_blocks(r))
    labels = segment_labels(r["points"], r["centre"], r["segments"]["start_deg"])
    seen = set()
    for row in rows:
        b, f, q = blocks[row["method"]], int(row["frame"]), row["component"]
        key = (row["method"], row["region"], row["index"], f, q)
        assert key not in seen
        seen.add(key)
        assert float(row["time_s"]) == r["frame_times_s"][f]
        if row["region"] == "pixel":
            p = int(row["index"])
            assert _num(row["value"]) == b["strain"][q][f][p]
            assert [float(row["x_px"]), float(row["y_px"])] == r["points"][p] and int(row["segment"]) == labels[p]
            sd = b["strain"].get(q + "_sd")
            assert _num(row["sd"]) == (None if sd is None else sd[f][p])
            if sd is not None:
                assert _num(row["lo"]) == pytest.approx(_num(row["value"]) - Z95 * sd[f][p], abs=1e-15)
        elif row["region"] == "global":
            assert row["index"] == row["segment"] == "" and _num(row["value"]) == b["global"][q][f]
            assert _num(row["hi"]) == (b["global"][q + "_hi"][f] if q + "_hi" in b["global"] else None)
        else:
            k = int(row["index"])
            assert int(row["segment"]) == k and row["x_px"] == ""
            for col, suffix in (("value", ""), ("sd", "_sd"), ("lo", "_lo"), ("hi", "_hi")):
                want = b["segments"][q + suffix][k][f] if q + suffix in b["segments"] else None
                assert _num(row[col]) == want, (key, col)
    if empty is not None:
        assert all(row["value"] == "" for row in rows if row["region"] == "segment" and row["index"] == str(empty))
