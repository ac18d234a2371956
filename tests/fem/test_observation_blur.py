"""The point-spread observation operator (Eq. 12 as a weighted average): weights, limits, exactness.

Properties checked against what they must be by construction, not against stored numbers: the rows'
weights sum to the PSF's tissue fraction (a background as bright as the tissue) or to 1 (a dark one);
a PSF narrowed to its centre gives the point interpolation; a symmetric PSF wholly inside the tissue
reports an affine field's value at its centre; the sample weights are those of the point
interpolation at each sample point.
"""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.fem.mesh import rectangle_mesh
from sfem_filters.fem.observation import (blurred_observation_matrix, interpolation_matrix, point_observation_matrix,
                                          sample_interpolation)

FAST = settings(max_examples=20, deadline=None)
MESH = rectangle_mesh(0.02, 0.012, 9, 6)                   # 20 mm x 12 mm, 2.5 / 2.4 mm elements


def _psf(sd, step=0.5e-3, radius=3.0):
    """Gaussian PSF samples (m) on a lattice of ``step``, cut at ``radius`` sd, weights summing to 1."""
    k = int(np.ceil(radius * sd / step))
    g = np.arange(-k, k + 1) * step
    off = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    w = np.exp(-0.5 * np.sum(off ** 2, axis=1) / sd ** 2)
    return off, w / w.sum()


points = st.lists(st.tuples(st.floats(0.0005, 0.0195), st.floats(0.0005, 0.0115)), min_size=1, max_size=6)


@FAST
@given(points, st.floats(0.4e-3, 2.0e-3))
def test_rows_sum_to_the_tissue_fraction_or_to_one(pts, sd):
    pts = np.array(pts)
    off, w = _psf(sd)
    N, inside = sample_interpolation(MESH, pts, off)
    fraction = (w[None] * inside).sum(axis=1)                           # the PSF's weight inside the mesh
    x_rows = slice(0, None, 2)
    lit = blurred_observation_matrix(MESH, pts, off, w, background=1.0)
    dark = blurred_observation_matrix(MESH, pts, off, w)
    assert np.allclose(np.asarray(lit.sum(axis=1)).ravel()[x_rows], fraction, atol=1e-12)
    assert np.allclose(np.asarray(dark.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    # inside test by geometry: the rectangle [0, 0.02] x [0, 0.012]
    q = pts[:, None] + off[None]
    geometric = (q[..., 0] >= 0) & (q[..., 0] <= 0.02) & (q[..., 1] >= 0) & (q[..., 1] <= 0.012)
    assert np.array_equal(inside, geometric)


@FAST
@given(points)
def test_a_psf_narrowed_to_its_centre_is_the_point_interpolation(pts):
    pts = np.array(pts)
    off, w = _psf(1e-6, step=0.5e-3)                                    # one sample carries all the weight
    assert off.shape[0] > 1
    D = blurred_observation_matrix(MESH, pts, off, np.where(np.all(off == 0, axis=1), 1.0, 0.0))
    assert abs(D - point_observation_matrix(MESH, pts)).max() < 1e-12
    off, w = _psf(0.05e-3, step=0.5e-3)                                 # a width far below the sampling
    D = blurred_observation_matrix(MESH, pts, off, w)
    assert abs(D - point_observation_matrix(MESH, pts)).max() < 1e-9


@FAST
@given(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.3, 0.3),
       st.floats(0.3e-3, 1.0e-3))
def test_a_symmetric_psf_inside_the_tissue_reports_an_affine_fields_value_at_its_centre(a, b, c, d, sd):
    A = np.array([[a, b], [c, d]])
    U = (MESH.nodes @ A.T + [1e-3, -2e-3]).ravel()
    pts = np.array([[0.01, 0.006], [0.0075, 0.0055]])
    off, w = _psf(sd)
    D = blurred_observation_matrix(MESH, pts, off, w)
    assert np.allclose((D @ U).reshape(-1, 2), pts @ A.T + [1e-3, -2e-3], atol=1e-12)


def test_the_samples_carry_the_point_interpolation_weights():
    pts = np.array([[0.004, 0.003], [0.0101, 0.0072]])
    off, _ = _psf(0.8e-3)
    N, inside = sample_interpolation(MESH, pts, off)
    q = (pts[:, None] + off[None]).reshape(-1, 2)
    keep = inside.ravel()
    assert keep.all()
    assert abs(N - interpolation_matrix(MESH, q)).max() < 1e-12
    out, inside = sample_interpolation(MESH, np.array([[0.0, 0.0]]), off)      # a corner: a quarter inside
    assert 0.2 < inside.mean() < 0.35
    assert np.all(np.asarray(out.sum(axis=1)).ravel()[~inside.ravel()] == 0)


def test_bad_weights_and_background_are_named():
    pts = np.array([[0.01, 0.006]])
    off, w = _psf(0.8e-3)
    with pytest.raises(ValueError, match="weights: expected non-negative PSF weights summing to 1"):
        blurred_observation_matrix(MESH, pts, off, 2 * w)
    with pytest.raises(ValueError, match="background: expected a non-negative"):
        blurred_observation_matrix(MESH, pts, off, w, background=-1.0)
    with pytest.raises(ValueError, match="points: expected every point's PSF to reach some tissue"):
        blurred_observation_matrix(MESH, np.array([[0.05, 0.05]]), off, w)
