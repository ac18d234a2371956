"""The closest point of a closed polyline (:func:`sfem_filters.imaging.contours.closest_on_polyline`), which the
border tracker and the DENSE route's guided border data search with."""
import numpy as np
from hypothesis import given, settings, strategies as st

from sfem_filters.imaging.contours import closest_on_polyline


def _star_polygon(radii, centre=(0.3, -0.2)):
    a = np.linspace(0.0, 2 * np.pi, len(radii), endpoint=False)
    return np.column_stack([centre[0] + radii * np.cos(a), centre[1] + radii * np.sin(a)])


@settings(max_examples=40, deadline=None)
@given(radii=st.lists(st.floats(0.5, 3.0), min_size=3, max_size=12),
       pts=st.lists(st.tuples(st.floats(-5, 5), st.floats(-5, 5)), min_size=1, max_size=8))
def test_the_closest_point_is_on_its_segment_and_no_sample_of_the_polyline_is_closer(radii, pts):
    curve = _star_polygon(np.array(radii))
    p = np.array(pts, float)
    q, seg, frac = closest_on_polyline(curve, p)
    a, b = curve, np.roll(curve, -1, axis=0)
    assert np.allclose(q, a[seg] + frac[:, None] * (b[seg] - a[seg]))          # on the segment it names
    t = np.linspace(0.0, 1.0, 400, endpoint=False)[:, None, None]
    samples = (a[None] + t * (b - a)[None]).reshape(-1, 2)
    nearest = np.min(np.linalg.norm(samples[None] - p[:, None], axis=2), axis=1)
    assert np.all(np.linalg.norm(q - p, axis=1) <= nearest + 1e-9)


def test_a_square_gives_its_sides_and_corners():
    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    q, _, _ = closest_on_polyline(square, np.array([[0.5, -1.0], [2.0, 2.0], [0.5, 0.4], [-0.2, 0.5]]))
    assert np.allclose(q, [[0.5, 0.0], [1.0, 1.0], [0.5, 0.0], [0.0, 0.5]])
