"""The truth's offset from the images (validation/_truth_offset.py; the strain_bands and border_views claims).

A truth offset from the images by ``s`` makes every estimate differ from it by ``s . grad(truth)``;
the fit must find ``s`` exactly where the first-order model is exact (a quadratic field: central
differences are exact, the curvature term is a per-frame constant the fit removes), and the
re-registered truth must be the field at the shifted points.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from sfem_filters.imaging import reference_points  # noqa: E402
from validation._truth_offset import fit_offset, grid_gradient, offset_equations, registered_truth  # noqa: E402

N = 40


def _annulus(inner=8.0, outer=15.0):
    yy, xx = np.mgrid[0:N, 0:N]
    d = np.hypot(xx - 19.3, yy - 20.1)
    return (d >= inner) & (d <= outer)


def _field(points, frames=4, shift=(0.0, 0.0)):
    """(F, P): a quadratic strain-like field growing over the frames, evaluated at points + shift."""
    x, y = points[:, 0] + shift[0] - 19.3, points[:, 1] + shift[1] - 20.1
    amp = np.linspace(0.2, 1.0, frames)[:, None]
    return amp * (0.01 * x + 0.004 * y + 2e-4 * x * x - 3e-4 * x * y + 1e-4 * y * y)


@settings(max_examples=25, deadline=None)
@given(st.floats(-0.7, 0.7), st.floats(-0.7, 0.7))
def test_the_offset_of_a_quadratic_truth_is_found_exactly(sx, sy):
    mask = _annulus()
    P = reference_points(mask)
    truth = _field(P)
    estimate = _field(P, shift=(sx, sy)) + 0.03                      # the tissue at X + s, plus a constant bias
    ij = P.astype(int)
    inner = ndimage.binary_erosion(mask, iterations=1)[ij[:, 1], ij[:, 0]]
    A, b = offset_equations(estimate, truth, *grid_gradient(P, truth, mask.shape), np.broadcast_to(inner, truth.shape))
    assert np.allclose(np.linalg.solve(A, b), [sx, sy], atol=1e-8)


def test_the_gradient_is_central_inside_and_one_sided_at_the_edge():
    mask = _annulus()
    P = reference_points(mask)
    v = (P[:, 0] ** 2)[None, :]                                       # d/dx = 2x centrally, 2x +- 1 one-sided
    gx, gy = grid_gradient(P, v, mask.shape)
    ij = P.astype(int)
    inside = ndimage.binary_erosion(mask, structure=np.array([[0, 0, 0], [1, 1, 1], [0, 0, 0]]))[ij[:, 1], ij[:, 0]]
    assert np.allclose(gx[0, inside], 2 * P[inside, 0])
    assert np.allclose(np.abs(gx[0, ~inside] - 2 * P[~inside, 0]), 1.0)
    assert np.allclose(gy, 0.0)


def test_the_re_registered_truth_is_the_field_at_the_shifted_points():
    mask = _annulus()
    P = reference_points(mask)
    linear = lambda s: np.linspace(0.5, 1.0, 3)[:, None] * (0.02 * (P[:, 0] + s[0]) - 0.01 * (P[:, 1] + s[1]))
    assert np.allclose(registered_truth(P, linear((0, 0)), mask.shape, (0.25, -0.4)), linear((0.25, -0.4)))


def test_a_truth_without_a_gradient_is_refused():
    mask = _annulus()
    P = reference_points(mask)
    flat = np.ones((3, len(P)))
    with pytest.raises(ValueError, match="truth: expected a strain gradient"):
        offset_equations(flat + 0.1, flat, *grid_gradient(P, flat, mask.shape), np.ones(flat.shape, bool))


def test_fit_offset_uses_the_inner_pixels_of_the_later_frames():
    """fit_offset on a case whose edge pixels and first frames are corrupted still finds the shift:
    only pixels two or more inside the mask, from a quarter of the frames on, enter."""
    mask = _annulus()
    P = reference_points(mask)
    truth = _field(P, frames=8)
    estimate = _field(P, frames=8, shift=(-0.25, 0.2))
    ij = P.astype(int)
    edge = ~ndimage.binary_erosion(mask, iterations=2)[ij[:, 1], ij[:, 0]]
    estimate[:, edge] += 0.5                                          # edge layers: a large error of their own
    estimate[:2] += np.random.default_rng(0).normal(0, 0.1, estimate[:2].shape)   # the first quarter: noise
    s, A, b = fit_offset(P, mask, estimate, truth)
    assert np.allclose(s, [-0.25, 0.2], atol=1e-8)
    assert np.allclose(np.linalg.solve(A, b), s)


def test_equations_are_weighted_by_the_precision_of_their_own_fit():
    """The same shifted field seen with noise of sd 2e-5 and 2e-4: the normal equations scale as
    1 / sigma^2, so their sum solves close to the precise one's answer, not midway."""
    mask = _annulus()
    P = reference_points(mask)
    truth = _field(P, frames=8)
    rng = np.random.default_rng(4)
    use = np.broadcast_to(ndimage.binary_erosion(mask, iterations=2)[P[:, 1].astype(int), P[:, 0].astype(int)],
                          truth.shape)
    g = grid_gradient(P, truth, mask.shape)
    fits = []
    for sd, shift in ((2e-5, (0.2, -0.1)), (2e-4, (-0.4, 0.3))):
        est = _field(P, frames=8, shift=shift) + sd * rng.standard_normal(truth.shape)
        fits.append(offset_equations(est, truth, *g, use))
    ratio = np.trace(fits[0][0]) / np.trace(fits[1][0])
    assert 50 < ratio < 200                                                    # (2e-4 / 2e-5)^2 = 100
    s = np.linalg.solve(fits[0][0] + fits[1][0], fits[0][1] + fits[1][1])
    assert np.allclose(s, (0.2, -0.1), atol=0.02)
