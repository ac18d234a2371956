"""Plane geometry on plain arrays (:mod:`sfem_filters.geometry`)."""
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from sfem_filters.geometry import nearest_on_closed_polyline


def _star_polygon(radii, centre=(0.3, -0.2)):
    a = np.linspace(0.0, 2 * np.pi, len(radii), endpoint=False)
    return np.column_stack([centre[0] + radii * np.cos(a), centre[1] + radii * np.sin(a)])


def _dense_samples(curve, per_edge=400):
    t = np.linspace(0.0, 1.0, per_edge, endpoint=False)[:, None, None]
    a, b = curve, np.roll(curve, -1, axis=0)
    return (a[None] + t * (b - a)[None]).reshape(-1, 2)


@settings(max_examples=40, deadline=None)
@given(radii=st.lists(st.floats(0.5, 3.0), min_size=3, max_size=12),
       pts=st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=1, max_size=8))
def test_the_nearest_point_is_on_the_polyline_and_no_sample_of_it_is_nearer(radii, pts):
    curve = _star_polygon(np.array(radii))
    p = np.array(pts, float)
    q = nearest_on_closed_polyline(curve, p)
    samples = _dense_samples(curve)
    d_q = np.linalg.norm(q - p, axis=1)
    d_best = np.min(np.linalg.norm(samples[None] - p[:, None], axis=2), axis=1)
    assert np.all(d_q <= d_best + 1e-9)                       # nothing on the curve is nearer
    # q lies on some edge: its distance to the nearest edge is zero
    a, b = curve, np.roll(curve, -1, axis=0)
    e = b - a
    t = np.clip(np.einsum("mnk,nk->mn", q[:, None] - a[None], e) / np.sum(e * e, 1), 0, 1)
    off = np.min(np.linalg.norm(a[None] + t[..., None] * e[None] - q[:, None], axis=2), axis=1)
    assert np.all(off < 1e-9)


def test_a_point_on_the_square_is_its_own_nearest_and_corners_and_sides_are_found():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    q = nearest_on_closed_polyline(square, np.array([[0.5, -1.0], [2.0, 2.0], [0.5, 0.4], [-0.2, 0.5], [1.0, 0.3]]))
    assert np.allclose(q, [[0.5, 0.0], [1.0, 1.0], [0.5, 0.0], [0.0, 0.5], [1.0, 0.3]])


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="curve_xy: expected"):
        nearest_on_closed_polyline(np.zeros((1, 2)), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="points: expected"):
        nearest_on_closed_polyline(np.eye(2), np.array([[np.nan, 0.0]]))
