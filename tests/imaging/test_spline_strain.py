"""The thin-plate spline's strain: exact for affine fields, its delta-method sd against Monte Carlo, bad input."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sfem_filters.imaging.spline_strain import spline_strain, tps_gradient_operators
from sfem_filters.imaging.strain import green_strain, project_strain

RNG = np.random.default_rng(0)
SITES = np.concatenate([np.column_stack([20 + r * np.cos(t), 20 + r * np.sin(t)])
                        for r, t in ((7, np.linspace(0, 2 * np.pi, 30, endpoint=False)),
                                     (13, np.linspace(0.1, 2 * np.pi + 0.1, 45, endpoint=False)))])
PIXELS = np.array([[x, y] for x in range(6, 35) for y in range(6, 35)
                   if 7.5 <= np.hypot(x - 20, y - 20) <= 12.5], float)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-0.4, 0.4), min_size=4, max_size=4), st.lists(st.floats(-3, 3), min_size=2, max_size=2),
       st.floats(0, 360))
def test_the_spline_strain_of_an_affine_field_is_exact(a, b, start):
    """Patch test: ``u = A X + b`` is reproduced exactly (no bending), so is its Green-Lagrange strain."""
    A = np.array(a).reshape(2, 2)
    u = (SITES @ A.T + np.array(b))[None]
    s = spline_strain(SITES, u, PIXELS, centre=(20.3, 19.8), start_deg=start)
    E = green_strain(np.broadcast_to(A, (1, len(PIXELS), 2, 2)))
    ecc, err, ecr = project_strain(E, PIXELS, (20.3, 19.8))
    np.testing.assert_allclose(s.Ecc, ecc, atol=1e-9)
    np.testing.assert_allclose(s.Err, err, atol=1e-9)
    np.testing.assert_allclose(s.Ecr, ecr, atol=1e-9)
    np.testing.assert_allclose(s.displacement[0], PIXELS @ A.T + np.array(b), atol=1e-9)
    np.testing.assert_allclose(s.global_curves["Ecc"], ecc.mean(axis=1), atol=1e-12)


def test_the_gradient_operator_matches_finite_differences_of_the_interpolant():
    y = RNG.normal(size=len(SITES))
    q = PIXELS[::7]
    h = 1e-5
    V, Ax, Ay = tps_gradient_operators(SITES, q)
    Vx, _, _ = tps_gradient_operators(SITES, q + [h, 0])
    Vy, _, _ = tps_gradient_operators(SITES, q + [0, h])
    np.testing.assert_allclose(Ax @ y, (Vx - V) @ y / h, atol=1e-4)
    np.testing.assert_allclose(Ay @ y, (Vy - V) @ y / h, atol=1e-4)
    V0, _, _ = tps_gradient_operators(SITES, SITES)                # an interpolant: it passes through the data
    np.testing.assert_allclose(V0 @ y, y, atol=1e-8)


def test_the_delta_method_sd_matches_a_monte_carlo_of_the_data_noise():
    """At zero displacement the strain is linear in the data to first order: the sd of many draws agrees."""
    sd = np.full((len(SITES), 2), 0.05)
    s = spline_strain(SITES, np.zeros((1, len(SITES), 2)), PIXELS, sd_px=sd, centre=(20, 20))
    draws = RNG.normal(0, 0.05, size=(400, len(SITES), 2))
    mc = spline_strain(SITES, draws, PIXELS, centre=(20, 20))
    np.testing.assert_allclose(mc.Ecc.std(axis=0), s.Ecc_sd[0], rtol=0.2)
    np.testing.assert_allclose(mc.Err.std(axis=0), s.Err_sd[0], rtol=0.2)
    np.testing.assert_allclose(mc.segment_curves["Ecc"].std(axis=1), s.segment_curves["Ecc_sd"][:, 0], rtol=0.2)
    np.testing.assert_allclose(mc.global_curves["Err"].std(), s.global_curves["Err_sd"][0], rtol=0.2)
    lo, hi = s.band("Ecc")
    assert np.all(lo < s.segment_curves["Ecc"]) and np.all(hi > s.segment_curves["Ecc"])


def test_without_an_sd_the_spline_has_no_band_and_says_so_in_its_json():
    s = spline_strain(SITES, np.zeros((2, len(SITES), 2)), PIXELS)
    d = s.to_dict()
    assert d["route"] == "spline" and d["strain"]["Ecc_sd"][0][0] is None and d["global"]["Ecc_lo"][0] is None
    assert d["strain"]["Ecc"][1][0] == 0.0


def test_a_frame_with_too_few_points_is_nan_and_the_others_are_not():
    u = np.zeros((2, len(SITES), 2))
    u[1, 2:] = np.nan
    s = spline_strain(SITES, u, PIXELS)
    assert np.all(np.isfinite(s.Ecc[0])) and np.all(np.isnan(s.Ecc[1]))


@pytest.mark.parametrize("kwargs, name", [
    ({"displacement_px": np.zeros((1, 5, 2))}, "displacement_px"),
    ({"sd_px": np.ones((3, 3))}, "sd_px"),
    ({"sd_px": -np.ones((len(SITES), 2))}, "sd_px"),
    ({"reference_pixels": np.zeros((0, 2))}, "reference_pixels"),
    ({"centre": (1, 2, 3)}, "centre"),
])
def test_bad_input_names_the_argument(kwargs, name):
    args = {"points_px": SITES, "displacement_px": np.zeros((1, len(SITES), 2)), "reference_pixels": PIXELS}
    args.update(kwargs)
    with pytest.raises(ValueError, match=name):
        spline_strain(**args)


def test_sites_on_one_line_are_refused():
    line = np.column_stack([np.arange(5.0), np.zeros(5)])
    with pytest.raises(ValueError, match="points"):
        tps_gradient_operators(line, PIXELS)
