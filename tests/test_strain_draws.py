"""The noise-draws claim's table (validation/strain_draws.py): draws counted per goal, the worst named, pooled coverage."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sfem_filters.benchmark import score_strain  # noqa: E402
from validation.strain_dense_sim import OURS, _better_conventional, draw_misses, goals_missed  # noqa: E402
from validation.strain_draws import markdown, pooled_coverage  # noqa: E402

METRICS = {"pixel_rmse_Ecc": 2.0, "pixel_rmse_Err": 5.0, "global_peak_error_Ecc": 0.3, "global_peak_error_Err": -2.0,
           "segment_peak_error_Ecc_mean": 0.5, "segment_peak_error_Err_mean": 3.0, "coverage_pct_Ecc": 95.0,
           "coverage_pct_Err": 95.0, "seconds": 10.0}


def _rows(seed: int, **ours) -> list:
    base = {"case": "heart", "snr": 8.0, "seed": seed, "n_points": 400}
    conv = [{**base, **METRICS, "method": f"conventional, sigma {s} px", "pixel_rmse_Ecc": 4.0 - s,
             "pixel_rmse_Err": 8.0} for s in (0, 1)]
    return conv + [{**base, **METRICS, "method": OURS, **ours}]


def _cells(text: str) -> list:
    return [c.strip() for c in next(ln for ln in text.splitlines() if ln.startswith("| heart")).strip("|").split("|")]


def test_a_missed_goal_is_counted_over_the_draws_and_named_with_its_worst_draw():
    rows = (_rows(3, coverage_pct_Ecc=83.0, global_peak_error_Err=-3.2, segment_peak_error_Err_mean=4.4)
            + _rows(4, global_peak_error_Err=+3.5, segment_peak_error_Err_mean=2.0, seconds=9.6)
            + _rows(5, coverage_pct_Ecc=80.5, coverage_pct_Err=85.0, pixel_rmse_Err=8.5))
    text = markdown({"rows": rows, "seeds": [3, 4, 5]})
    cells = _cells(text)
    assert cells[2] == "0 of 3"                               # every draw misses something
    assert cells[3] == "-1.00 / +0.50"                        # Ecc: 2.0 against the better conventional's 3.0
    assert cells[4] == "+0.30 / +3.50"                        # the peak error furthest from zero, with its sign
    assert cells[5] == "0.50 / 4.40"                          # the largest mean segment peak error
    assert cells[6] == "80.5 to 95.0" and cells[7] == "85.0 to 95.0"
    assert cells[8] == "82.8 to 95.0"                         # seed 5 pooled: (80.5 + 85.0) / 2
    assert cells[9] == "10"                                   # the longest run's seconds
    assert ("heart SNR 8: RMSE Err in 1 of 3 (worst: RMSE Err +0.50 above the better conventional); "
            "global peak Err in 2 of 3 (worst: global peak Err +3.50); segment peak Err in 1 of 3 (worst: segment "
            "peak Err 4.40); coverage Ecc in 2 of 3 (worst: coverage Ecc 80.5%); pooled coverage outside 85-99% in "
            "1 of 3") in text
    assert "seeds 3 to 5" in text


def test_an_rmse_equal_to_the_conventional_is_a_miss_and_a_nan_figure_is_the_worst():
    rows = _rows(3, pixel_rmse_Ecc=3.0) + _rows(4, segment_peak_error_Ecc_mean=float("nan")) + _rows(5)
    text = markdown({"rows": rows, "seeds": [3, 4, 5]})
    assert _cells(text)[2] == "1 of 3"
    assert "RMSE Ecc in 1 of 3 (worst: RMSE Ecc +0.00 above the better conventional)" in text
    assert "segment peak Ecc in 1 of 3 (worst: segment peak Ecc nan)" in text
    # the strain page's own summary sees the NaN draw too, even behind a finite one that misses
    both = _rows(0, segment_peak_error_Err_mean=float("nan")) + _rows(1, segment_peak_error_Err_mean=9.0)
    assert goals_missed({"rows": both}) == ["heart SNR 8: segment peak Err nan"]


def test_every_goal_met_at_every_draw_says_so():
    text = markdown({"rows": _rows(3) + _rows(4), "seeds": [3, 4]})
    assert "Every goal is met at every draw, on both readings of the band goal." in text
    assert "| heart | 8 | 2 of 2 |" in text


def test_the_pooled_coverage_is_the_scorings_own_pooled_count():
    rng = np.random.default_rng(0)
    pts = np.array([[np.cos(a), np.sin(a)] for a in np.radians(np.arange(5, 360, 10))]) * 10 + 20
    F, P = 12, len(pts)
    te, tr = -0.1 * rng.random((F, P)), 0.3 * rng.random((F, P))
    ee, er = te + 0.02 * rng.standard_normal((F, P)), tr + 0.05 * rng.standard_normal((F, P))
    bands = {q: (np.full((6, F), lo), np.full((6, F), hi)) for q, lo, hi in (("Ecc", -0.08, -0.02), ("Err", 0.1, 0.2))}
    s = score_strain(ee, er, te, tr, pts, [20, 20], ecc_band=bands["Ecc"], err_band=bands["Err"])
    assert 0 < s.coverage_pct_Ecc < 100 and 0 < s.coverage_pct_Err < 100 and s.coverage_pct_Ecc != s.coverage_pct_Err
    assert pooled_coverage(s.to_dict()) == pytest.approx(s.coverage_pct)


def test_draw_misses_uses_the_strain_pages_goals():
    rows = _rows(0, global_peak_error_Err=-3.2, segment_peak_error_Err_mean=4.1, coverage_pct_Err=99.5, seconds=200.0)
    missed = draw_misses(rows[-1], _better_conventional(rows))
    assert list(missed) == ["global peak Err", "segment peak Err", "coverage Err", "time"]
    assert missed["global peak Err"][1] == "global peak Err -3.20" and missed["time"][1] == "time 200 s"
    assert draw_misses(_rows(1)[-1], _better_conventional(_rows(1))) == {}
