"""A heart turned by a quarter turn on the pixel grid is the same heart: the DENSE readers, the
conventional analysis and the DENSE route must say so, on a given DENSE-Sim case with its own truth.

The turn maps the grid onto itself, so every array moves exactly; the displacement vectors turn
with it, so the two encodings swap and one changes sign. Radial and circumferential strain about
the (turned) centre do not change. A convention that mixes x and y, or a sign of an encoding, in
the reader, the Eulerian inversion, the centre or the segments would show here as a different
strain; the mesh (Gmsh meshes the turned outline afresh) is the one thing that may differ.
"""
import os
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from sfem_filters.imaging import add_complex_noise, conventional_analysis, read_dense_sim, truth_at_points

DATA = Path(os.environ.get("SFEM_FILTERS_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
CASE = DATA / "dense_sim" / "phantom_subject_1"
FRAMES = 6

pytestmark = pytest.mark.skipif(not (CASE / "config.yaml").is_file(),
                                reason=f"the DENSE-Sim case is not here ({CASE}); set SFEM_FILTERS_DATA")


def quarter_turn(case):
    """``case`` turned by ``numpy.rot90`` (a pixel at x, y goes to y, W - 1 - x; a vector (u, v) to (v, -u))."""
    def rot(a):
        return None if a is None else np.ascontiguousarray(np.rot90(a, 1, axes=(-2, -1)))
    px, py = case.phases
    phases = np.stack([rot(py), np.angle(np.exp(-1j * rot(px))).astype(case.phases.dtype)])
    return replace(case, phases=phases, magnitude=rot(case.magnitude), masks=rot(case.masks),
                   truth_ecc=rot(case.truth_ecc), truth_err=rot(case.truth_err))


def _first_frames(case, n):
    return replace(case, phases=case.phases[:, :n], magnitude=case.magnitude[:n], masks=case.masks[:n + 1],
                   frame_times_s=case.frame_times_s[:n], truth_ecc=case.truth_ecc[:n], truth_err=case.truth_err[:n])


def _turned_order(case):
    """Index of each reference pixel of ``case`` among the turned case's reference pixels (row-major both)."""
    H, W = case.reference_mask.shape
    rows, cols = np.nonzero(case.reference_mask)
    turned = np.zeros((W, H), int) - 1
    r2, c2 = np.nonzero(np.rot90(case.reference_mask))
    turned[r2, c2] = np.arange(r2.size)
    return turned[W - 1 - cols, rows]


@pytest.fixture(scope="module")
def cases():
    case = _first_frames(add_complex_noise(read_dense_sim(CASE), 30.0, 0), FRAMES)
    return case, quarter_turn(case), _turned_order(case)


def test_the_turned_truth_is_the_same_strain_at_the_same_tissue(cases):
    case, turned, order = cases
    assert np.all(order >= 0)
    for a, b in zip(truth_at_points(case), truth_at_points(turned)):
        assert np.array_equal(a, b[:, order], equal_nan=True)


def test_the_conventional_analysis_does_not_see_the_turn(cases):
    case, turned, order = cases
    # a direction at angle a about the centre turns to a - 90 degrees: segments from 270 are the same tissue
    a, b = conventional_analysis(case, sigma=1.0), conventional_analysis(turned, sigma=1.0, start_deg=270.0)
    for q in ("Ecc", "Err"):
        ea, eb = getattr(a.strain, q), getattr(b.strain, q)[:, order]
        ok = np.isfinite(ea)
        assert np.array_equal(ok, np.isfinite(eb)) and ok.mean() > 0.9
        assert np.max(np.abs(ea[ok] - eb[ok])) < 1e-6
        assert np.allclose(getattr(a, f"global_{q}"), getattr(b, f"global_{q}"), atol=1e-9)
        assert np.allclose(getattr(a, f"segments_{q}"), getattr(b, f"segments_{q}"), atol=1e-9)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
def test_the_dense_route_sees_the_same_strain_and_the_same_error_after_the_turn(cases):
    from sfem_filters.benchmark import score_strain
    from sfem_filters.cardiac import dense_case_strain, image_settings

    case, turned, order = cases
    r = dense_case_strain(case, image_settings(case))
    s = dense_case_strain(turned, image_settings(turned, start_deg=270.0))
    # pixel by pixel the two differ by the mesh (Gmsh meshes the turned outline afresh); the yardstick of
    # how much a mesh change moves the curves is measured here, on the unturned case, by an element of
    # 2.6 px instead of 2.5 (at the time of writing the turn moved the curves 0.8-1.8 times as much as
    # that): a convention the turn breaks moves them far more
    m = dense_case_strain(case, replace(image_settings(case), element_px=2.6))
    for q in ("Ecc", "Err"):
        mesh_global = np.max(np.abs(r.global_curves[q] - m.global_curves[q]))
        mesh_segments = np.max(np.abs(r.segment_curves[q] - m.segment_curves[q]))
        assert 0 < mesh_global and 0 < mesh_segments          # the yardstick itself is measured
        assert np.max(np.abs(r.global_curves[q] - s.global_curves[q])) < 3 * mesh_global
        assert np.max(np.abs(r.segment_curves[q] - s.segment_curves[q])) < 3 * mesh_segments
    truth = truth_at_points(case)
    sa = score_strain(r.Ecc, r.Err, *truth, r.points, r.centre)
    sb = score_strain(s.Ecc[:, order], s.Err[:, order], *truth, r.points, r.centre)
    assert sb.pixel_rmse_Err == pytest.approx(sa.pixel_rmse_Err, rel=0.1)
    assert sb.pixel_rmse_Ecc == pytest.approx(sa.pixel_rmse_Ecc, rel=0.1)
