"""The spec's strain metrics on tiny hand-made arrays with known answers (strain in percentage points)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from sfem_filters.benchmark.strain_scoring import StrainScore, score_strain
from sfem_filters.imaging.strain import segment_labels

C = np.array([10.0, 10.0])
# one pixel in each of the six 60-degree segments (angles 30, 90, ..., 330 from +x towards +y)
ANG = np.radians(30 + 60 * np.arange(6))
PTS = C + 4 * np.column_stack([np.cos(ANG), np.sin(ANG)])
PTS = np.round(PTS)                       # pixel centres; the angles stay inside their segments


def test_segments_of_the_fixture():
    assert segment_labels(PTS, C).tolist() == [0, 1, 2, 3, 4, 5]


def test_pixel_rmse_uses_only_pairs_where_both_are_finite():
    truth = np.zeros((2, 6))
    est = truth.copy()
    est[0, :3] = 0.03                     # 3 of 12 values off by 3 points
    est[1, 5] = np.nan                    # left out, and so is its truth
    s = score_strain(est, truth, truth, truth, PTS, C)
    assert s.pixel_rmse_Ecc == pytest.approx(np.sqrt(3 * 9 / 11))
    assert s.pixel_rmse_Err == pytest.approx(0.0)
    assert (s.n_valid, s.n_total) == (11, 12)
    t = truth.copy()
    t[0, 0] = np.nan                      # a missing truth leaves that pair out too
    assert score_strain(est, truth, t, truth, PTS, C).pixel_rmse_Ecc == pytest.approx(np.sqrt(2 * 9 / 10))


def test_global_peaks_each_at_its_own_frame():
    truth_ecc = np.array([[-0.05] * 6, [-0.10] * 6, [-0.02] * 6])          # min -10 at frame 1
    est_ecc = np.array([[-0.12] * 6, [-0.08] * 6, [-0.02] * 6])            # min -12 at frame 0
    truth_err = np.array([[0.1] * 6, [0.3] * 6, [0.2] * 6])                # max 30 at frame 1
    est_err = np.array([[0.1] * 6, [0.2] * 6, [0.25] * 6])                 # max 25 at frame 2
    s = score_strain(est_ecc, est_err, truth_ecc, truth_err, PTS, C)
    assert s.global_peak_Ecc == pytest.approx(-12) and s.global_peak_Ecc_truth == pytest.approx(-10)
    assert s.global_peak_error_Ecc == pytest.approx(-2.0)
    assert s.global_peak_error_Err == pytest.approx(-5.0)


def test_segment_peak_errors_mean_and_max_of_absolute_values():
    truth = np.tile([[0.0], [0.2], [0.1]], (1, 6))                         # every segment peaks at 20
    est = truth.copy()
    est[1] += np.array([0.01, -0.02, 0.0, 0.0, 0.03, 0.0])                 # segment peak errors 1, -2, 0, 0, 3, 0
    s = score_strain(-truth, est, -truth, truth, PTS, C)
    assert s.segment_peak_error_Err_mean == pytest.approx(1.0)
    assert s.segment_peak_error_Err_max == pytest.approx(3.0)
    assert s.segment_peak_error_Ecc_mean == pytest.approx(0.0)
    shifted = score_strain(-truth, est, -truth, truth, PTS, C, start_deg=60)  # same pixels, labels turned
    assert shifted.segment_peak_error_Err_max == pytest.approx(3.0)


def test_coverage_and_band_width():
    truth = np.tile([[0.0], [0.1]], (1, 6))                                 # segment means 0 and 10 points
    seg_true = np.tile([[0.0, 0.1]], (6, 1))
    lo, hi = seg_true - 0.01, seg_true + 0.01                              # 2 points wide, all inside
    hi[0, 1] = 0.095                                                       # one pair misses (0.5 wide)
    lo[3, 0] = np.nan                                                      # one pair has no band: left out
    s = score_strain(truth, truth, truth, truth, PTS, C, ecc_band=(lo, hi), err_band=(seg_true - 0.02,
                                                                                      seg_true + 0.02))
    assert s.coverage_pct_Ecc == pytest.approx(100 * 10 / 11)
    assert s.band_width_Ecc == pytest.approx((10 * 2.0 + 0.5) / 11)
    assert s.coverage_pct_Err == pytest.approx(100.0) and s.band_width_Err == pytest.approx(4.0)
    assert s.coverage_pct == pytest.approx(100 * 22 / 23)
    none = score_strain(truth, truth, truth, truth, PTS, C)
    assert none.coverage_pct is None and none.band_width_Err is None


def test_to_dict_is_json_ready_and_frozen():
    truth = np.zeros((2, 6))
    s = score_strain(truth, truth, truth, truth, PTS, C)
    d = s.to_dict()
    assert set(d) == set(StrainScore.__dataclass_fields__) and json.loads(json.dumps(d)) == d
    with pytest.raises(Exception):
        s.pixel_rmse_Ecc = 1.0


def test_errors_name_the_argument():
    truth = np.zeros((2, 6))
    with pytest.raises(ValueError, match="truth_err: expected shape"):
        score_strain(truth, truth, truth, np.zeros((3, 6)), PTS, C)
    with pytest.raises(ValueError, match="ecc: expected shape"):
        score_strain(np.zeros((2, 5)), truth, truth, truth, PTS, C)
    with pytest.raises(ValueError, match="ecc_band: expected lower bounds"):
        score_strain(truth, truth, truth, truth, PTS, C, ecc_band=(np.ones((6, 2)), np.zeros((6, 2))))
    with pytest.raises(ValueError, match=r"ecc_band\[0\]: expected shape"):
        score_strain(truth, truth, truth, truth, PTS, C, ecc_band=(np.ones((6, 3)), np.ones((6, 3))))
    with pytest.raises(ValueError, match="expected some"):
        score_strain(np.full((2, 6), np.nan), truth, truth, truth, PTS, C)


def test_pixel_and_global_band_coverage_and_width():
    truth = np.tile([[0.0], [0.1]], (1, 6))                                 # 2 frames, 6 pixels
    lo, hi = truth - 0.01, truth + 0.01                                    # pixel bands 2 points wide
    hi[1, 2] = 0.095                                                       # one (frame, pixel) pair misses
    g = truth.mean(axis=1)                                                 # global curve 0 and 10 points
    s = score_strain(truth, truth, truth, truth, PTS, C, pixel_bands={"Ecc": (lo, hi), "Err": (lo, hi)},
                     global_bands={"Ecc": (g - 0.03, g + 0.03), "Err": (g + 0.001, g + 0.03)})
    assert s.coverage_pct_pixels_Ecc == pytest.approx(100 * 11 / 12)
    assert s.band_width_pixels_Ecc == pytest.approx((11 * 2.0 + 0.5) / 12)
    assert s.coverage_pct_global_Ecc == pytest.approx(100.0) and s.band_width_global_Ecc == pytest.approx(6.0)
    assert s.coverage_pct_global_Err == pytest.approx(0.0)                 # the band sits above the truth
    assert s.coverage_pct_Ecc is None                                      # no segment bands given
    with pytest.raises(ValueError, match="global_bands"):
        score_strain(truth, truth, truth, truth, PTS, C, global_bands={"Ecc": (g, g)})


def test_coverage_at_the_peak_reads_each_curves_own_peak_frame():
    """Three frames; each segment's truth peaks (Err: max) at a frame of its own; a band that misses only there
    drops the peak coverage and barely the all-frame coverage."""
    F = 3
    peak_frame = np.array([0, 1, 2, 0, 1, 2])
    seg_true = np.full((6, F), 0.05)
    seg_true[np.arange(6), peak_frame] = 0.20                     # the peaks
    truth = seg_true.T.copy()                                     # one pixel a segment: (F, 6)
    lo, hi = seg_true - 0.01, seg_true + 0.01
    hi[[1, 4], peak_frame[[1, 4]]] = 0.15                         # two segments' bands miss at their peak only
    lo[[1, 4], peak_frame[[1, 4]]] = 0.10
    s = score_strain(-truth, truth, -truth, truth, PTS, C, ecc_band=(-seg_true - 0.01, -seg_true + 0.01),
                     err_band=(lo, hi), global_bands={"Ecc": (-truth.mean(1) - 0.01, -truth.mean(1) + 0.01),
                                                      "Err": (truth.mean(1) - 0.01, truth.mean(1) - 0.005)})
    assert s.coverage_pct_peak_Err == pytest.approx(100 * 4 / 6)
    assert s.coverage_pct_Err == pytest.approx(100 * 16 / 18)
    assert s.coverage_pct_peak_Ecc == pytest.approx(100.0)        # Ecc's peak is its minimum: the same frames
    assert s.coverage_pct_global_peak_Ecc == 100.0 and s.coverage_pct_global_peak_Err == 0.0
    none = score_strain(truth, truth, truth, truth, PTS, C)
    assert none.coverage_pct_peak_Err is None and none.coverage_pct_global_peak_Err is None
