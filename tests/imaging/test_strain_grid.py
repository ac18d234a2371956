"""Green-Lagrange strain on the reference pixel grid: analytic deformations, directions, smoothing, curves."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.imaging.dense import reference_points
from sfem_filters.imaging.strain import (curve_peak, displacement_gradient, global_curve, green_strain, mask_centre,
                                         project_strain, radial_circumferential, segment_curves, segment_labels,
                                         small_strain, smooth_in_mask, strain_on_grid)


def ring_points(c=(14.3, 15.6), r_in=5.0, r_out=10.0, n=32):
    yy, xx = np.mgrid[0:n, 0:n]
    r = np.hypot(xx - c[0], yy - c[1])
    return reference_points((r >= r_in) & (r <= r_out))


@st.composite
def masks(draw):
    """A random blob of pixels (a union of rectangles) with at least a few 4-connected pairs."""
    m = np.zeros((16, 16), bool)
    for _ in range(draw(st.integers(1, 4))):
        r0, c0 = draw(st.integers(0, 12)), draw(st.integers(0, 12))
        m[r0:r0 + draw(st.integers(2, 4)), c0:c0 + draw(st.integers(2, 4))] = True
    return m


def rotation(th):
    return np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])


@settings(max_examples=40, deadline=None)
@given(m=masks(), th=st.floats(-np.pi, np.pi), t=st.tuples(st.floats(-5, 5), st.floats(-5, 5)))
def test_rigid_rotation_has_zero_green_strain(m, th, t):
    X = reference_points(m)
    c = X.mean(axis=0)
    u = (X - c) @ (rotation(th) - np.eye(2)).T + np.asarray(t)
    G = displacement_gradient(X, u)
    has = np.isfinite(G).all(axis=(1, 2))
    assert has.any()
    assert np.abs(green_strain(G[has])).max() < 1e-12
    if abs(th) > 0.05:                                     # the small strain is not rotation-free
        assert np.abs(small_strain(G[has])).max() == pytest.approx(1 - np.cos(th), rel=1e-9)


@settings(max_examples=40, deadline=None)
@given(m=masks(), lx=st.floats(0.5, 1.6), ly=st.floats(0.5, 1.6), th=st.floats(-np.pi, np.pi))
def test_uniform_stretch_gives_its_analytic_green_strain(m, lx, ly, th):
    X = reference_points(m)
    R = rotation(th)
    Fm = R @ np.diag([lx, ly]) @ R.T                      # stretches along axes turned by th
    u = X @ (Fm - np.eye(2)).T
    G = displacement_gradient(X, u)
    has = np.isfinite(G).all(axis=(1, 2))
    want = R @ np.diag([(lx ** 2 - 1) / 2, (ly ** 2 - 1) / 2]) @ R.T
    assert np.allclose(green_strain(G[has]), want, atol=1e-12)      # one-sided differences too: affine


def test_central_where_both_neighbours_one_sided_otherwise():
    m = np.zeros((3, 6), bool)
    m[1, 1:5] = True                                      # a row of 4 pixels, x = 1..4
    X = reference_points(m)
    u = np.column_stack([X[:, 0] ** 2, np.zeros(len(X))])
    G = displacement_gradient(X, u)
    # x = 1: forward 4 - 1 = 3; x = 2: central (9 - 1) / 2 = 4; x = 3: central 6; x = 4: backward 16 - 9 = 7
    assert np.allclose(G[:, 0, 0], [3, 4, 6, 7])
    assert np.isnan(G[:, :, 1]).all()                     # no vertical neighbour at all: NaN, not zero
    u[1] = np.nan                                         # an untracked point becomes an absent neighbour
    G = displacement_gradient(X, u[None])[0]
    assert np.isnan(G[1]).all() and G[0, 0, 0] == pytest.approx(np.nan, nan_ok=True)
    assert G[2, 0, 0] == pytest.approx(7.0)               # forward from x = 3 to 4


def test_radial_and_circumferential_directions_and_dilation():
    X = ring_points()
    m = np.zeros((32, 32), bool)
    m[X[:, 1].astype(int), X[:, 0].astype(int)] = True
    c = mask_centre(m)
    assert np.allclose(c, X.mean(axis=0))
    er, ec = radial_circumferential(np.array([[5.0, 0.0], [0.0, 5.0]]), [0.0, 0.0])
    assert np.allclose(er, [[1, 0], [0, 1]]) and np.allclose(ec, [[0, 1], [-1, 0]])    # +90 deg in image axes
    s = strain_on_grid(X, (0.2 * (X - c))[None], centre=c)
    assert np.allclose(s.Ecc, (1.2 ** 2 - 1) / 2) and np.allclose(s.Err, (1.2 ** 2 - 1) / 2)
    assert np.allclose(s.Ecr, 0, atol=1e-12)
    tw = strain_on_grid(X, ((X - c) @ (rotation(0.3) - np.eye(2)).T)[None], centre=c)
    assert np.abs(tw.E).max() < 1e-12                     # twist of the whole slice: no strain


def test_radial_thickening_projects_on_err():
    X = ring_points()
    c = X.mean(axis=0)
    d = X - c
    r = np.linalg.norm(d, axis=1)
    u = d * (0.05 + 0.0 * r)[:, None]
    u = u + d / r[:, None] * 0.1 * (r - 7.5)[:, None]       # u_r = 0.05 r + 0.1 (r - 7.5): du_r/dr = 0.15
    s = strain_on_grid(X, u[None], centre=c)
    inner = (r > 6.5) & (r < 9)
    err_want = ((1.15) ** 2 - 1) / 2
    ecc_want = ((1 + 0.05 + 0.1 * (r - 7.5) / r) ** 2 - 1) / 2
    assert np.abs(s.Err[0, inner] - err_want).max() < 0.02
    assert np.abs(s.Ecc[0, inner] - ecc_want[inner]).max() < 0.02


def test_smoothing_inside_the_mask_does_not_leak():
    X = ring_points()
    v = np.full((1, len(X)), 3.0)
    assert np.allclose(smooth_in_mask(X, v, 1.5), 3.0)    # a constant stays constant at the border
    c = X.mean(axis=0)
    lin = (X[:, 0] - c[0])[None] * 0.1
    sm = smooth_in_mask(X, lin, 1.0)
    assert abs(sm.mean() - lin.mean()) < 1e-2
    vv = v.copy()
    vv[0, 0] = np.nan
    out = smooth_in_mask(X, vv, 1.0)
    assert np.isnan(out[0, 0]) and np.allclose(out[0, 1:], 3.0)
    assert np.array_equal(smooth_in_mask(X, lin, 0.0), lin)
    s = strain_on_grid(X, (0.2 * (X - c))[None], centre=c, sigma=1.0, smooth="strain")
    assert np.allclose(s.Ecc, 0.22, atol=1e-9) and s.smoothed == "strain"      # a uniform strain stays
    # smoothing the displacement pulls border values inwards: the radial strain across a 5-px wall flattens
    s = strain_on_grid(X, (0.2 * (X - c))[None], centre=c, sigma=1.0, smooth="displacement")
    assert abs(s.Ecc.mean() - 0.22) < 0.01 and s.Err.mean() < 0.8 * 0.22 and s.smoothed == "displacement"
    with pytest.raises(ValueError, match="smooth"):
        strain_on_grid(X, (0.2 * (X - c))[None], sigma=1.0, smooth="phase")
    with pytest.raises(ValueError, match="sigma"):
        smooth_in_mask(X, v, -1.0)


def test_segments_from_the_start_angle():
    c = np.array([10.0, 10.0])
    ang = np.radians([5, 65, 125, 185, 245, 305, 359])
    X = c + 4 * np.column_stack([np.cos(ang), np.sin(ang)])
    assert segment_labels(X, c).tolist() == [0, 1, 2, 3, 4, 5, 5]
    assert segment_labels(X, c, start_deg=30).tolist() == [5, 0, 1, 2, 3, 4, 5]
    assert segment_labels(X, c, start_deg=-60).tolist() == [1, 2, 3, 4, 5, 0, 0]
    # y points down: a point below the centre (y > cy) is at +90 degrees
    assert segment_labels([[10.0, 14.0]], c).tolist() == [1]


def test_curves_and_peaks():
    v = np.array([[1.0, 3.0, np.nan], [np.nan, np.nan, np.nan], [-2.0, 0.0, 2.0]])
    assert np.allclose(global_curve(v), [2.0, np.nan, 0.0], equal_nan=True)
    seg = segment_curves(v, [0, 0, 5])
    assert seg.shape == (6, 3) and np.allclose(seg[0], [2.0, np.nan, -1.0], equal_nan=True)
    assert np.isnan(seg[1]).all()
    assert curve_peak([0.1, -0.3, -0.2], "min") == (-0.3, 1)
    assert curve_peak([0.1, np.nan, 0.4], "max") == (0.4, 2)
    with pytest.raises(ValueError, match="kind"):
        curve_peak([1.0], "peak")


def test_bad_points_are_named():
    with pytest.raises(ValueError, match="points: expected pixel centres"):
        displacement_gradient([[0.5, 1.0], [1.5, 1.0]], np.zeros((2, 2)))
    with pytest.raises(ValueError, match="points: expected distinct"):
        displacement_gradient([[1.0, 1.0], [1.0, 1.0]], np.zeros((2, 2)))
    with pytest.raises(ValueError, match="displacement: expected shape"):
        displacement_gradient([[1.0, 1.0], [2.0, 1.0]], np.zeros((3, 2)))
    with pytest.raises(ValueError, match="centre: expected a centre off every point"):
        radial_circumferential([[1.0, 1.0]], [1.0, 1.0])
    E = np.zeros((1, 2, 2))
    assert [a.shape for a in project_strain(E, [[2.0, 1.0]], [0.0, 0.0])] == [(1,), (1,), (1,)]
