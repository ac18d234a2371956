"""Synthetic motion drawn on a mesh finer than any estimator's (``truth_element_px``): the field at
the pixels converges as the mesh is refined, so the finest draw stands for the continuum, and the
default draw (node-per-pixel mesh) is unchanged."""
from __future__ import annotations

import numpy as np
import pytest

from sfem_filters.cardiac import annulus_sequence

#: Deterministic motion: undeclared effects only, springs at (almost) noise-free landmarks, (almost)
#: no process noise, so that draws on different meshes differ by their discretisation alone.
_QUIET = dict(amplitude=((0.15, -0.3), (0.0, 0.3)), seed=0, n_frames=6, noise_px=1e-6, landmark_step_px=1e-9,
              return_truth=True)
_EFFECTS = ["active_polar", "active_helical"]


def _truth(element_px):
    return annulus_sequence(_EFFECTS, truth_element_px=element_px, **_QUIET)[1]["displacement"]


@pytest.fixture(scope="module")
def reference():
    return _truth(0.5)


def test_the_field_at_the_pixels_converges_as_the_truth_mesh_is_refined(reference):
    assert np.isfinite(reference).all() and np.sqrt(np.mean(reference ** 2)) > 0.3   # it moves (px)
    err = {h: np.sqrt(np.mean((_truth(h) - reference) ** 2)) for h in (2.0, 1.0, 0.7)}
    assert err[2.0] > err[1.0] > err[0.7]
    # linear triangles: the error falls about as h^2 (a factor of 4 from 2 to 1 px; at least 2.5)
    assert err[2.0] / err[1.0] > 2.5
    assert err[0.7] < 0.03 * np.sqrt(np.mean(reference ** 2))


def test_the_node_per_pixel_draw_pays_a_discretisation_error_against_the_fine_one(reference):
    """The inverse crime the option removes: the default draw and an estimator on the same mesh
    share a discretisation; against the fine draw, the node-per-pixel mesh misses by as much as a
    2-pixel polar mesh does, far more than the 0.7-pixel one."""
    node = annulus_sequence(_EFFECTS, **_QUIET)[1]["displacement"]
    assert node.shape == reference.shape
    e_node = np.sqrt(np.mean((node - reference) ** 2))
    e_fine = np.sqrt(np.mean((_truth(0.7) - reference) ** 2))
    assert e_node > 3 * e_fine


def test_the_sequence_says_how_it_was_drawn_and_bad_sizes_are_named():
    seq = annulus_sequence(None, n_frames=4, truth_element_px=1.0)
    assert "truth_element_px=1.0" in seq.provenance
    assert "truth_element_px" not in annulus_sequence(None, n_frames=4).provenance
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="truth_element_px"):
            annulus_sequence(None, n_frames=4, truth_element_px=bad)
