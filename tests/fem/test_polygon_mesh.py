"""Meshes of polygonal regions at a chosen element size (Gmsh, an optional dependency)."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.fem.mesh import TriMesh, mesh_quality
from sfem_filters.geometry import signed_area

gmsh = pytest.importorskip("gmsh", reason="gmsh (the optional mesher, GPL-2.0-or-later) is not installed")

from sfem_filters.fem.polygon_mesh import circle_polygon, edge_lengths, polygon_mesh, resample_polygon  # noqa: E402


@settings(max_examples=15, deadline=None)
@given(r_in=st.floats(3.0, 8.0), wall=st.floats(2.0, 6.0), size=st.floats(0.6, 2.0),
       cx=st.floats(-20.0, 20.0), scale=st.sampled_from([1.0, 1.75e-3]))
def test_an_annulus_is_covered_by_good_triangles_of_the_asked_size(r_in, wall, size, cx, scale):
    centre = np.array([cx, 0.5 * cx]) * scale
    outer = circle_polygon(centre, (r_in + wall) * scale, 0.25 * size * scale)
    inner = circle_polygon(centre + 0.2 * wall * scale, r_in * scale, 0.25 * size * scale)
    mesh = polygon_mesh(outer, [inner], size=size * scale)
    assert isinstance(mesh, TriMesh)
    # the mesh covers the region bounded by the resampled borders exactly (no gap, no overlap) ...
    region = (abs(signed_area(resample_polygon(outer, size * scale)))
              - abs(signed_area(resample_polygon(inner, size * scale))))
    assert mesh.areas.sum() == pytest.approx(region, rel=1e-9)
    # ... and that region is the annulus up to the chords' sagitta (h^2 / 8 r per unit length)
    exact = np.pi * ((r_in + wall) ** 2 - r_in ** 2) * scale ** 2
    assert abs(mesh.areas.sum() - exact) / exact < 0.05
    q = mesh_quality(mesh)
    assert q["min_angle_deg"] > 20.0
    lengths = edge_lengths(mesh) / scale
    assert 0.75 * size < np.mean(lengths) < 1.25 * size
    assert np.max(lengths) < 2.0 * size
    # every node on a border lies on it: radii of the boundary nodes are those of the circles (to the sagitta)
    r = np.linalg.norm(mesh.nodes[mesh.boundary_nodes()] - centre, axis=1) / scale
    r_hole = np.linalg.norm(mesh.nodes[mesh.boundary_nodes()] - (centre + 0.2 * wall * scale), axis=1) / scale
    on_outer = np.abs(r - (r_in + wall)) < 0.1 * size
    on_inner = np.abs(r_hole - r_in) < 0.1 * size
    assert np.all(on_outer | on_inner)


def test_a_finer_size_gives_more_elements_of_the_same_quality():
    outer = circle_polygon([0, 0], 10.0, 0.5)
    inner = circle_polygon([0, 0], 6.0, 0.5)
    coarse, fine = polygon_mesh(outer, [inner], size=2.0), polygon_mesh(outer, [inner], size=1.0)
    assert 3.0 < fine.n_elements / coarse.n_elements < 5.0          # area per element ~ size^2
    assert mesh_quality(fine)["min_angle_deg"] > 20.0


def test_a_square_without_holes():
    sq = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])
    mesh = polygon_mesh(sq, size=1.0)
    assert mesh.areas.sum() == pytest.approx(16.0)
    assert np.allclose(mesh.nodes.min(axis=0), 0.0) and np.allclose(mesh.nodes.max(axis=0), 4.0)


@pytest.mark.parametrize("outer, holes, size, match", [
    (np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]), (), 1.0, "outer"),
    (np.array([[0.0, 0.0], [1.0, 0.0]]), (), 1.0, "outer"),
    (np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]]), (), 0.0, "size"),
    (np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]]), [np.zeros((3, 2))], 1.0, r"holes\[0\]"),
])
def test_bad_input_names_the_argument(outer, holes, size, match):
    with pytest.raises(ValueError, match=match):
        polygon_mesh(outer, holes, size=size)
