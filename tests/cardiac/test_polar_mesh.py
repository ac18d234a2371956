"""A mesh chosen apart from the points (``mesh="polar"``): the mesh, the shape-function map to the
points, and the model built on it against the node-per-point model it generalises."""
from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.cardiac import (NotStarShapedError, annulus_sequence, closing_the_loop, lv_geometry, polar_mesh,
                                   prepare)
from sfem_filters.cardiac.measured import at_points, build_model, point_rows
from sfem_filters.cardiac.specs import EstimatorSettings, LoopSettings, ModelSpec
from sfem_filters.fem.observation import interpolation_matrix
from sfem_filters.geometry import triangle_double_areas


def _circle(r, n=90, centre=(0.0, 0.0)):
    a = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a)])


def _wiggly():
    """A contour that is not star-shaped about the origin: a ray from it crosses the contour thrice."""
    t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    r = 15.0 + 9.0 * np.sin(3 * t)
    return np.column_stack([r * np.cos(t) + 12 * np.cos(9 * t), r * np.sin(t) + 12 * np.sin(9 * t)])


def test_polar_mesh_of_a_ring_covers_it_with_the_asked_edge_and_is_an_annulus():
    mesh = polar_mesh(_circle(10.0), _circle(15.0), (0.0, 0.0), size=2.0)
    area = 0.5 * np.abs(triangle_double_areas(mesh.nodes, mesh.elements)).sum()
    n = round(np.pi * 25.0 / 2.0)
    assert mesh.n_nodes == n * (round(5.0 / 2.0) + 1)                 # rings x (layers + 1)
    # the ring's area, less the chords' cut (polygons of n sides)
    assert area == pytest.approx(0.5 * n * np.sin(2 * np.pi / n) * (15.0 ** 2 - 10.0 ** 2), rel=1e-9)
    g = lv_geometry(mesh)
    assert len(g.endo) == n and len(g.epi) == n
    edges = np.linalg.norm(mesh.nodes[mesh.elements] - np.roll(mesh.nodes[mesh.elements], 1, axis=1), axis=2)
    assert 1.0 < np.median(edges) < 3.5


def test_polar_mesh_refuses_a_contour_that_is_not_star_shaped_naming_it():
    # a C-shaped epicardium seen from the centre: a ray crosses it three times
    wiggly = _wiggly()
    with pytest.raises(ValueError, match="epi_xy"):
        polar_mesh(_circle(3.0), wiggly, (0.0, 0.0), size=2.0)
    with pytest.raises(ValueError, match="size"):
        polar_mesh(_circle(10.0), _circle(15.0), (0.0, 0.0), size=0.0)
    with pytest.raises(ValueError, match="epi_xy"):
        polar_mesh(_circle(15.0), _circle(10.0), (0.0, 0.0), size=2.0)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-3, 3), min_size=6, max_size=6), st.integers(0, 10_000))
def test_interpolation_reproduces_every_affine_field_at_points_inside(coef, seed):
    mesh = polar_mesh(_circle(10.0), _circle(15.0), (0.0, 0.0), size=2.0)
    rng = np.random.default_rng(seed)
    r, a = rng.uniform(10.5, 14.5, 40), rng.uniform(0, 2 * np.pi, 40)
    pts = np.column_stack([r * np.cos(a), r * np.sin(a)])
    A = np.array(coef).reshape(2, 3)
    field = mesh.nodes @ A[:, :2].T + A[:, 2]
    W = interpolation_matrix(mesh, pts)
    assert np.allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0)
    assert np.allclose(W @ field, pts @ A[:, :2].T + A[:, 2], atol=1e-9)


def test_interpolation_clamps_points_just_outside_and_refuses_points_far_outside():
    mesh = polar_mesh(_circle(10.0), _circle(15.0), (0.0, 0.0), size=2.0)
    near = np.array([[15.05, 0.0]])
    W = interpolation_matrix(mesh, near, max_outside=0.1)
    assert np.allclose(W.sum(), 1.0) and np.all(W.data >= 0)
    assert np.linalg.norm(W @ mesh.nodes - near) < 0.1
    with pytest.raises(ValueError, match="points"):
        interpolation_matrix(mesh, np.array([[17.0, 0.0]]), max_outside=0.1)


@pytest.fixture(scope="module")
def sequences():
    seq = annulus_sequence(None, n_frames=5, seed=2)
    return seq, prepare(seq, 8), prepare(seq, 8, mesh="polar", element_px=2.0)


def test_polar_setup_keeps_the_points_contours_and_carries_nodal_values_to_the_points(sequences):
    seq, nodes, polar = sequences
    assert polar.mesh.n_nodes < nodes.mesh.n_nodes / 2                 # the cost is the mesh's
    assert polar.point_mesh.n_nodes == seq.n_points and polar.node_of_point is None
    np.testing.assert_array_equal(polar.landmarks, nodes.landmarks)   # the points' landmarks and split
    np.testing.assert_array_equal(polar.heldout, nodes.heldout)
    xy = at_points(polar, polar.mesh.nodes[None])[0]                   # coordinates: an affine field
    assert np.max(np.linalg.norm(xy - seq.points * polar.spacing, axis=1)) < 0.5 * polar.spacing
    W = polar.interpolation.tocsr()
    assert W.data.min() >= 0 and np.diff(W.indptr).max() <= 3        # one triangle's three nodes each
    assert np.allclose(np.asarray(W.sum(axis=1)).ravel(), 1.0)
    D = point_rows(polar, polar.observed)
    assert D.shape == (2 * len(polar.observed), polar.mesh.n_dofs)
    with pytest.raises(ValueError, match="element_px"):
        prepare(seq, 8, mesh="polar", element_px=-1.0)


@pytest.mark.parametrize("drive", ["penalty", "contour"])
def test_springs_through_shape_functions_are_the_node_springs_when_each_point_is_a_node(sequences, drive):
    """The general drive (a spring at a point through the shape functions: D^T k c D) with the
    identity as the shape-function map is the node-per-point drive: the same stiffness, loads,
    observation rows and covariance of the spring loads."""
    seq, nodes, _ = sequences
    P = seq.n_points
    general = dataclasses.replace(nodes, interpolation=sp.identity(P, format="csr"), node_of_point=None)
    m0, y0 = build_model(nodes, drive=drive)
    m1, y1 = build_model(general, drive=drive)
    np.testing.assert_allclose(y1, y0)
    np.testing.assert_allclose(m1.penalty, m0.penalty, rtol=1e-12, atol=0)
    np.testing.assert_allclose(m1.loads, m0.loads, rtol=1e-12, atol=1e-30)
    np.testing.assert_allclose(m1.observation_operator.toarray(), m0.observation_operator.toarray())
    np.testing.assert_allclose(m1.Q, m0.Q, rtol=1e-9, atol=1e-12 * np.abs(m0.Q).max())


def test_rounds_on_a_polar_mesh_with_warm_starts_and_screening_run_and_say_so(sequences):
    seq, _, _ = sequences
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        out = closing_the_loop(seq, ModelSpec(mesh="polar"), EstimatorSettings(max_iterations=3),
                               LoopSettings(max_rounds=1, warm_start=True, screen_iterations=1, corrections=False))
    cfg = out.as_json()["config"]
    assert cfg["mesh"] == "polar" and cfg["element_px"] == 2.0 and cfg["warm_start"] is True
    assert cfg["screen_iterations"] == 1 and cfg["mesh_nodes"] == out.setup.mesh.n_nodes
    assert np.isfinite(out.extended.metrics["heldout_rmse_px"])
    with pytest.raises(ValueError, match="screen_iterations"):
        closing_the_loop(seq, estimator=EstimatorSettings(estimator="cyclic"),
                         loop=LoopSettings(effects="none", screen_iterations=2))
    with pytest.raises(ValueError, match="warm_start"):
        LoopSettings(effects="none", warm_start="yes")


@pytest.mark.needs_data("subject_a")
def test_the_command_line_searches_and_each_option_overrides_its_search(monkeypatch):
    from sfem_filters.cardiac import SEARCHES, closing
    from sfem_filters.cli import main
    seen = {}

    def fake(seq, model, estimator, loop, **how):       # the rounds themselves are tested above
        seen.clear()
        seen.update({**model.to_json(), **estimator.to_json(), **loop.to_json(), **how})
        raise SystemExit(0)

    defaults = {**ModelSpec().to_json(), **EstimatorSettings().to_json(), **LoopSettings().to_json()}
    monkeypatch.setattr(closing, "closing_the_loop", fake)
    with pytest.raises(SystemExit):
        main(["dense", "example", "--search", "full", "--no-progress"])
    # the full search: the library's defaults, every one passed (a batch fingerprint hashes them all)
    for key in ("mesh", "warm_start", "screen_iterations", "stiff_springs", "laplace", "measurement_noise"):
        assert seen[key] == defaults[key], key
    assert seen["max_iterations"] == 20
    with pytest.raises(SystemExit):
        main(["dense", "example", "--search", "fast", "--no-progress"])
    fast = SEARCHES["fast"]
    assert seen["mesh"] == fast.mesh == "delaunay"                   # the node-per-point mesh
    assert (seen["warm_start"], seen["screen_iterations"]) == (True, fast.screen_iterations)
    assert seen["max_iterations"] == fast.max_iterations("penalty") == 40
    with pytest.raises(SystemExit):
        main(["dense", "example", "--no-progress"])                   # the default search: coarse
    coarse = SEARCHES["coarse"]
    assert (seen["mesh"], seen["element_px"], seen["warm_start"], seen["screen_iterations"]) == \
        (coarse.mesh, coarse.element_px, True, coarse.screen_iterations)
    with pytest.raises(SystemExit):
        main(["dense", "example", "--search", "coarse", "--mesh", "delaunay", "--no-warm-start",
              "--screen-iterations", "0", "--max-iterations", "7", "--no-progress"])
    assert (seen["mesh"], seen["warm_start"], seen["screen_iterations"], seen["max_iterations"]) == \
        ("delaunay", False, None, 7)
    with pytest.raises(SystemExit):
        main(["dense", "example", "--search", "full", "--mesh", "polar", "--element-px", "3", "--no-progress"])
    assert seen["mesh"] == "polar" and seen["element_px"] == 3.0 and seen["warm_start"] is False


def test_polar_mesh_says_not_star_shaped_with_its_own_error():
    wiggly = _wiggly()
    with pytest.raises(NotStarShapedError, match="star-shaped"):
        polar_mesh(_circle(3.0), wiggly, (0.0, 0.0), size=2.0)
    assert issubclass(NotStarShapedError, ValueError)


@pytest.mark.needs_data("subject_a")
def test_a_search_on_a_polar_mesh_falls_back_to_the_points_mesh_where_the_wall_is_not_star_shaped(
        monkeypatch, capsys):
    """The search's polar mesh cannot follow a wall that is not star-shaped about its centre: the
    command says so in one line and meshes through the points; asked for by name, the error stands."""
    from sfem_filters.cardiac import closing
    from sfem_filters.cli import main
    calls = []

    def fake(seq, model, estimator, loop, **how):
        config = {**model.to_json(), **estimator.to_json(), **loop.to_json(), **how}
        calls.append(config)
        if config.get("mesh") == "polar":
            raise NotStarShapedError("epi_xy: expected a contour star-shaped about the cavity centre")
        raise SystemExit(0)

    monkeypatch.setattr(closing, "closing_the_loop", fake)
    with pytest.raises(SystemExit):
        main(["dense", "example", "--search", "coarse", "--no-progress"])
    assert [c["mesh"] for c in calls] == ["polar", "delaunay"]
    assert {**calls[0], "mesh": "delaunay"} == calls[1]
    err = capsys.readouterr().err
    assert "warning: --search coarse: epi_xy" in err and "--mesh delaunay" in err
    calls.clear()
    assert main(["dense", "example", "--search", "coarse", "--mesh", "polar", "--no-progress"]) != 0
    assert len(calls) == 1 and "star-shaped" in capsys.readouterr().err
