"""The noise-draws claim's table (validation/strain_draws.py): draws counted per goal, the worst named, pooled coverage."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from validation.strain_dense_sim import OURS, _better_conventional, draw_misses  # noqa: E402
from validation.strain_draws import markdown, pooled_coverage  # noqa: E402

METRICS = {"pixel_rmse_Ecc": 2.0, "pixel_rmse_Err": 5.0, "global_peak_error_Ecc": 0.3, "global_peak_error_Err": -2.0,
           "segment_peak_error_Ecc_mean": 0.5, "segment_peak_error_Err_mean": 3.0, "coverage_pct_Ecc": 95.0,
           "coverage_pct_Err": 95.0, "seconds": 10.0}


def _rows(seed: int, **ours) -> list:
    base = {"case": "heart", "snr": 8.0, "seed": seed, "n_points": 400}
    conv = [{**base, **METRICS, "method": f"conventional, sigma {s} px", "pixel_rmse_Ecc": 4.0 - s,
             "pixel_rmse_Err": 8.0} for s in (0, 1)]
    return conv + [{**base, **METRICS, "method": OURS, **ours}]


def test_a_missed_goal_is_counted_over_the_draws_and_named_with_its_worst_draw():
    rows = _rows(3, coverage_pct_Ecc=83.0) + _rows(4) + _rows(5, coverage_pct_Ecc=80.5, coverage_pct_Err=85.0, pixel_rmse_Err=8.5)
    text = markdown({"rows": rows, "seeds": [3, 4, 5]})
    cells = [c.strip() for c in next(ln for ln in text.splitlines() if ln.startswith("| heart")).strip("|").split("|")]
    assert cells[2] == "1 of 3"                               # only seed 4 meets every goal
    assert cells[3] == "-1.00 / +0.50"                        # Ecc: 2.0 against the better conventional's 3.0
    assert cells[6] == "80.5 to 95.0" and cells[7] == "85.0 to 95.0"
    assert cells[8] == "82.8 to 95.0"                         # seed 5 pooled: (80.5 + 85.0) / 2
    assert "heart SNR 8: RMSE Err in 1 of 3 (worst: RMSE Err +0.50 above the better conventional); " \
           "coverage Ecc in 2 of 3 (worst: coverage Ecc 80.5%); pooled coverage outside 85-99% in 1 of 3" in text
    assert "seeds 3 to 5" in text


def test_every_goal_met_at_every_draw_says_so():
    text = markdown({"rows": _rows(3) + _rows(4), "seeds": [3, 4]})
    assert "Every goal is met at every draw, on both readings of the band goal." in text
    assert "| heart | 8 | 2 of 2 |" in text


@pytest.mark.parametrize("ecc, err, pooled", [(80.0, 96.0, 88.0), (99.5, 99.5, 99.5)])
def test_pooled_coverage_weighs_the_two_bands_of_each_segment_frame_alike(ecc, err, pooled):
    assert pooled_coverage({"coverage_pct_Ecc": ecc, "coverage_pct_Err": err}) == pytest.approx(pooled)


def test_draw_misses_uses_the_strain_pages_goals():
    rows = _rows(0, global_peak_error_Err=-3.2, segment_peak_error_Err_mean=4.1, coverage_pct_Err=99.5, seconds=200.0)
    missed = draw_misses(rows[-1], _better_conventional(rows))
    assert list(missed) == ["global peak Err", "segment peak Err", "coverage Err", "time"]
    assert missed["global peak Err"][1] == "global peak Err -3.20" and missed["time"][1] == "time 200 s"
