"""Shared pytest configuration and hypothesis strategies."""
from __future__ import annotations

import os
import pathlib

import numpy as np
import pytest
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from sfem_filters import datasets
from sfem_filters.fem.mesh import delaunay_mesh

# ---------------------------------------------------------------------------
# Third-party data sets (sfem_filters.datasets): not in the package. The tests read them from the
# data directory SFEM_FILTERS_DATA, set here to the project's ../shared/data when unset and present
# (subprocesses inherit it). A test that needs one is marked ``@pytest.mark.needs_data("name")``:
# without it, the test is skipped with the reason and how to get it, except in CI (CI=true), which
# has the data, where a missing data set is an error.
# ---------------------------------------------------------------------------
SHARED_DATA = pathlib.Path(__file__).resolve().parents[2] / "shared" / "data"
if not os.environ.get(datasets.ENV_VAR) and SHARED_DATA.is_dir():
    os.environ[datasets.ENV_VAR] = str(SHARED_DATA)


def in_ci() -> bool:
    return os.environ.get("CI", "").strip().lower() in ("true", "1", "yes")


def pytest_configure(config):
    config.addinivalue_line("markers", "needs_data(*names): the test reads these registered data sets "
                                       "(sfem_filters.datasets); skipped without them, an error in CI")


#: The test files that take minutes (every claim's quick tier, the documentation build, the examples), collected
#: first: scripts/test.sh hands whole files to its two workers in collection order (pytest-xdist
#: ``--dist loadfile --no-loadscope-reorder``; by default xdist orders files by their number of tests), so these
#: start at once and the short files fill in around them, rather than one of them
#: starting last and running alone while the other worker idles (longest first).
LONG_FILES = ("test_validation_suite.py", "test_docs.py", "test_examples.py")


def pytest_collection_modifyitems(session, config, items):
    rank = {name: k for k, name in enumerate(LONG_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(LONG_FILES)))     # stable: the rest keep their order


def pytest_runtest_setup(item):
    for marker in item.iter_markers("needs_data"):
        for name in marker.args:
            try:
                datasets.dataset_path(name)
                continue
            except datasets.DatasetNotFoundError as exc:
                missing = str(exc)
            if in_ci():
                pytest.fail(f"CI=true but the data set is missing:\n{missing}", pytrace=False)
            pytest.skip(f"data set {name!r} not found: set {datasets.ENV_VAR} to a folder with "
                        f"{datasets.DATASETS[name].path}, or run sfem_filters.datasets.fetch({name!r})")


# ---------------------------------------------------------------------------
# Hypothesis strategies for meshes and materials
# (used by test_mesh.py, test_fem.py, test_strain_statistics.py)
# ---------------------------------------------------------------------------

# Lattice spacing of the random point clouds, about 1 mm. A power of two keeps lattice
# coordinates exact, so collinear points stay exactly collinear: with decimal steps (1e-3 m)
# round-off makes them nearly collinear and scipy's Delaunay can return a zero-area hull
# triangle, which delaunay_mesh rejects (see test_mesh.py::test_delaunay_nearly_collinear_hull).
LATTICE_STEP_M = 2.0 ** -10


def _not_collinear(coords) -> bool:
    pts = np.array(coords, float)
    return np.linalg.matrix_rank(pts - pts[0]) == 2


@st.composite
def lattice_point_clouds(draw, min_points=4, max_points=30, extent=40):
    """Distinct, not-all-collinear points on a ~1 mm integer lattice (metres).

    Lattice points make exact collinearity and cocircularity likely (hard cases for
    Delaunay) while keeping every non-degenerate triangle's area far above round-off.
    """
    coords = draw(st.lists(st.tuples(st.integers(0, extent), st.integers(0, extent)),
                           min_size=min_points, max_size=max_points, unique=True)
                  .filter(_not_collinear))
    offset = draw(st.tuples(st.integers(-100, 100), st.integers(-100, 100)))
    return (np.array(coords, float) + np.array(offset, float)) * LATTICE_STEP_M


@st.composite
def jittered_grid_meshes(draw, max_nodes_per_side=6):
    """Delaunay mesh of a rectangle grid with randomly jittered interior nodes (metres, a few cm)."""
    nx = draw(st.integers(3, max_nodes_per_side))
    ny = draw(st.integers(3, max_nodes_per_side))
    width = draw(st.floats(0.005, 0.05))
    height = draw(st.floats(0.005, 0.05))
    jitter = draw(st.floats(0.0, 0.2))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    X, Y = np.meshgrid(np.linspace(0.0, width, nx), np.linspace(0.0, height, ny))
    pts = np.column_stack([X.ravel(), Y.ravel()])
    interior = ((X > 0) & (X < width) & (Y > 0) & (Y < height)).ravel()
    # Only interior nodes move, so the outline stays a rectangle (no hull slivers to peel).
    step = np.array([width / (nx - 1), height / (ny - 1)])
    pts[interior] += jitter * rng.uniform(-1.0, 1.0, (interior.sum(), 2)) * step
    return delaunay_mesh(pts, min_angle_deg=1.0)


def element_materials(n_elements, E_min=1e3, E_max=1e6, nu_min=0.05, nu_max=0.49):
    """Per-element Young's moduli (Pa) and Poisson's ratios as a strategy of (E, nu) arrays."""
    E = hnp.arrays(float, n_elements, elements=st.floats(E_min, E_max))
    nu = hnp.arrays(float, n_elements, elements=st.floats(nu_min, nu_max))
    return st.tuples(E, nu)


@st.composite
def meshes_with_materials(draw):
    """A jittered-grid mesh with random per-element E (Pa) and nu."""
    mesh = draw(jittered_grid_meshes())
    E, nu = draw(element_materials(mesh.n_elements))
    return mesh, E, nu
