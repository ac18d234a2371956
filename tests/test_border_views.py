"""The border-views claim's measurements (validation/border_views.py) on cases of known answer."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.special import ndtr

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from validation.border_views import (fit_blurred_wall, magnitude_wall, mask_wall,  # noqa: E402
                                     mean_along_rays, summary)


def _wall_profile(r, a, b, sigma, levels=(0.4, 1.0, 0.1)):
    c, m, o = levels
    inner, outer = ndtr((r - a) / sigma), ndtr((r - b) / sigma)
    return c * (1 - inner) + m * (inner - outer) + o * outer


@settings(max_examples=25, deadline=None)
@given(a=st.floats(3.0, 6.0), thick=st.floats(3.0, 8.0), sigma=st.floats(0.5, 1.2),
       da=st.floats(-0.8, 0.8), db=st.floats(-0.8, 0.8), cavity=st.floats(0.0, 0.6))
def test_blurred_wall_fit_recovers_the_radii_of_a_blurred_wall(a, thick, sigma, da, db, cavity):
    r = np.arange(0.0, a + thick + 5.0, 0.25)
    b = a + thick
    prof = _wall_profile(r, a, b, sigma, (cavity, 1.0, 0.12))[None]
    fa, fb = fit_blurred_wall(prof, r, np.array([a + da]), np.array([b + db]), sigma)
    assert fa[0] == pytest.approx(a, abs=1e-3) and fb[0] == pytest.approx(b, abs=1e-3)


def test_mask_wall_measures_a_pixel_ring_to_its_quantisation():
    yy, xx = np.mgrid[0:96, 0:96]
    centre = np.array([47.5, 47.5])
    d = np.hypot(xx - centre[0], yy - centre[1])
    mask = (d >= 12.0) & (d <= 20.0)
    angles = np.linspace(0, 2 * np.pi, 120, endpoint=False)
    a, b = mask_wall(mask, centre, angles)
    assert np.all(np.abs(a - 12.0) <= 1.0) and np.all(np.abs(b - 20.0) <= 1.0)
    assert np.mean(b - a) == pytest.approx(8.0, abs=0.5)
    with pytest.raises(ValueError, match="mask"):
        mask_wall(np.zeros_like(mask), centre, angles)


def test_magnitude_wall_finds_the_edges_of_a_blurred_ring_image_not_the_masks():
    """A ring image whose edges sit half a pixel inside a fatter mask: the fit finds the image's edges."""
    yy, xx = np.mgrid[0:96, 0:96]
    centre = np.array([47.3, 48.1])
    d = np.hypot(xx - centre[0], yy - centre[1])
    image = _wall_profile(d, 12.6, 19.4, 0.8, (0.3, 1.0, 0.1))
    mask = (d >= 12.0) & (d <= 20.0)
    angles = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    a, b = magnitude_wall(image, centre, angles, 0.8, mask_wall(mask, centre, angles))
    assert np.median(np.abs(a - 12.6)) < 0.05 and np.median(np.abs(b - 19.4)) < 0.05


def test_mean_along_rays_of_a_field_and_the_summary_of_views():
    field = np.full((40, 40), np.nan)
    field[10:30, 10:30] = 2.5
    centre = np.array([20.0, 20.0])
    angles = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    v = mean_along_rays(field, centre, angles, np.full(8, 2.0), np.full(8, 8.0))
    assert np.allclose(v, 2.5)
    views = {"case": "c", "thickening": {"truth": [0.0, 0.2, 0.1], "masks": [0.0, 0.2, 0.1],
                                        "magnitude": [0.0, 0.1, 0.1], "phase": [0.0, 0.3, 0.1]}}
    rows = {r["view"]: r for r in summary(views)}
    assert rows["masks"]["error_at_peak"] == 0.0 and rows["masks"]["rms_error"] == 0.0
    assert rows["magnitude"]["error_at_peak"] == pytest.approx(-0.1)
    assert rows["phase"]["radial_strain_error_at_peak"] == pytest.approx((1.3 ** 2 - 1.2 ** 2) / 2)


def test_truth_offset_recovers_a_known_shift_of_a_smooth_truth():
    """Strain that is the truth sampled a known sub-pixel offset away: the fit finds the offset and the moved truth fits."""
    from types import SimpleNamespace
    from validation.border_views import truth_offset
    yy, xx = np.mgrid[0:64, 0:64].astype(float)
    centre = np.array([31.7, 32.2])
    d = np.hypot(xx - centre[0], yy - centre[1])
    mask = (d >= 10) & (d <= 18)
    delta = np.array([-0.25, 0.15])

    def field(x, y, t):
        r = np.hypot(x - centre[0], y - centre[1])
        return t * (0.3 - 0.01 * r + 0.02 * np.cos(np.arctan2(y - centre[1], x - centre[0])))
    times = np.array([0.2, 0.6, 1.0])
    truth = np.stack([np.where(mask, field(xx, yy, t), np.nan) for t in times])
    rows, cols = np.nonzero(mask)
    est = np.stack([field(cols + delta[0], rows + delta[1], t) for t in times])
    case = SimpleNamespace(reference_mask=mask, truth_ecc=truth, truth_err=truth)
    conv = {1.0: SimpleNamespace(strain=SimpleNamespace(Ecc=est, Err=est))}
    rows_out = truth_offset(case, conv, "ring")
    for r in rows_out:
        assert r["delta_x_px"] == pytest.approx(delta[0], abs=0.02)
        assert r["delta_y_px"] == pytest.approx(delta[1], abs=0.02)
        assert r["segment_rms_error_truth_moved"] < 0.2 * r["segment_rms_error"]
