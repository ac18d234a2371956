"""The DENSE route's recovered gradient, its pixel variance, and the honest bands' two terms
(maximum-likelihood noise scale, empirical-Bayes excess error against the linearised finite-difference strain)."""
import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.ndimage import gaussian_filter1d

pytest.importorskip("gmsh", reason="gmsh (the optional mesher, GPL-2.0-or-later) is not installed")

from helpers import thickening_ring_tracks  # noqa: E402
from sfem_filters.cardiac.annulus import annulus_mask  # noqa: E402
from sfem_filters.cardiac.strain_bands import (  # noqa: E402
    curve_curvature,
    curve_noise_variance,
    discrepancy_variance,
    excess_variance,
    linearised_disagreement,
    linearised_rows,
    noise_scale,
    point_variance,
)
from sfem_filters.cardiac.strain_route import (  # noqa: E402
    PROCESS_FRACTIONS,
    StrainRouteSettings,
    concentrated_log_evidence,
    curve_discrepancy,
    dense_strain,
    gradient_operators,
    process_fraction_ml,
    reference_mesh,
)
from sfem_filters.imaging.strain import (displacement_gradient, green_strain, project_strain,  # noqa: E402
                                         radial_circumferential, segment_curves)
from sfem_filters.imaging.dense import LagrangianDisplacement, reference_points  # noqa: E402

PX = 1.75e-3


MASK = annulus_mask(4.0, 8.5, 24)
MESH = reference_mesh(MASK, PX, "gmsh", 2.0)
POINTS = reference_points(MASK) * PX


def _point_gradients(ops, weights, U):
    return np.stack([weights @ (op @ U) for op in ops], axis=-1).reshape(-1, 2, 2)


@settings(max_examples=20, deadline=None)
@given(st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6), st.sampled_from(["recovered", "element"]))
def test_both_gradients_reproduce_an_affine_displacement_exactly(coefs, kind):
    """The patch test: an affine field's constant gradient at every point, whichever gradient."""
    A = np.array(coefs[:4]).reshape(2, 2)
    U = (MESH.nodes @ A.T + np.array(coefs[4:]) * PX).ravel()
    ops, weights = gradient_operators(MESH, POINTS, kind)
    assert np.allclose(_point_gradients(ops, weights, U), A, atol=1e-10)
    assert np.allclose(np.asarray(weights.sum(axis=1)).ravel(), 1.0)


def test_the_recovered_gradient_is_continuous_and_the_element_gradient_is_not():
    """A quadratic field: the element gradient jumps across edges; the recovered one does not, and is closer."""
    c = MESH.nodes.mean(axis=0)
    d = (MESH.nodes - c) / PX
    U = (np.column_stack([d[:, 0] ** 2, d[:, 0] * d[:, 1]]) * 1e-3 * PX).ravel()
    x = (POINTS - c) / PX
    exact = 1e-3 * np.stack([np.column_stack([2 * x[:, 0], 0 * x[:, 0]]), np.column_stack([x[:, 1], x[:, 0]])],
                            axis=1)
    errs = {}
    for kind in ("recovered", "element"):
        ops, weights = gradient_operators(MESH, POINTS, kind)
        errs[kind] = np.sqrt(np.mean((_point_gradients(ops, weights, U) - exact) ** 2))
    assert errs["recovered"] < 0.7 * errs["element"]


def test_point_variance_is_exact_for_elements_and_an_upper_bound_for_recovered_gradients():
    rng = np.random.default_rng(3)
    n = MESH.n_dofs
    L = rng.standard_normal((n, n)) / np.sqrt(n)
    Cu = L @ L.T + 0.1 * np.eye(n)
    a = rng.standard_normal((1, len(POINTS), 4))
    for kind in ("element", "recovered"):
        ops, weights = gradient_operators(MESH, POINTS, kind)
        C_items = np.zeros((1, ops[0].shape[0], 4, 4))
        O = [op.toarray() for op in ops]
        for i in range(4):
            for j in range(4):
                C_items[0, :, i, j] = np.einsum("md,de,me->m", O[i], Cu, O[j])
        approx = point_variance(weights, a, C_items)[0]
        R = [(weights @ op).toarray() for op in ops]                       # (P, n) each
        rows = sum(a[0, :, k][:, None] * R[k] for k in range(4))
        exact = np.einsum("pd,de,pe->p", rows, Cu, rows)
        if kind == "element":
            assert np.allclose(approx, exact, rtol=1e-10)
        else:
            assert np.all(approx >= exact * (1 - 1e-10)) and np.any(approx > exact * 1.01)


def _ar1(rng, F, rho, sd):
    """Noise correlated over frames (AR(1), lag-1 correlation rho), as the phase texture is."""
    e = np.empty(F)
    e[0] = rng.standard_normal()
    for t in range(1, F):
        e[t] = rho * e[t - 1] + np.sqrt(1 - rho ** 2) * rng.standard_normal()
    return sd * e


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-0.4, 0.4), min_size=8, max_size=8), st.floats(0.0, 2 * np.pi))
def test_the_linearised_disagreement_is_the_green_difference_less_its_quadratic_term(g, angle):
    """``e.E(G + D)e - e.E(G)e = (F e).(D e) + |D e|^2 / 2`` exactly, for both directions."""
    G = np.array(g[:4]).reshape(1, 1, 2, 2)
    Dg = np.array(g[4:]).reshape(1, 1, 2, 2)
    X = np.array([[np.cos(angle), np.sin(angle)]]) * 5.0
    c = np.zeros(2)
    a_cc, a_rr = linearised_rows(G, X, c)
    ecc0, err0, _ = project_strain(green_strain(G), X, c)
    ecc1, err1, _ = project_strain(green_strain(G + Dg), X, c)
    er, ec = radial_circumferential(X, c)
    for a, d_green, e in ((a_cc, ecc1 - ecc0, ec[0]), (a_rr, err1 - err0, er[0])):
        lin = linearised_disagreement(G + Dg, G, a)
        assert np.allclose(lin + 0.5 * np.sum((Dg[0, 0] @ e) ** 2), d_green, atol=1e-12)


def test_the_linearised_disagreement_has_no_noise_bias_and_the_green_difference_has_its_variance():
    """Zero-mean gradient noise of sd s: the Green difference is biased by E|n e|^2 / 2 = s^2, the linearised
    disagreement is not (the cause of the SNR-8 bands that were too wide)."""
    rng = np.random.default_rng(11)
    P, s = 4000, 0.08
    ang = rng.uniform(0, 2 * np.pi, P)
    X = np.column_stack([np.cos(ang), np.sin(ang)]) * 10.0
    c = np.zeros(2)
    G = np.broadcast_to(np.array([[0.1, -0.05], [0.02, -0.08]]), (1, P, 2, 2))
    noisy = G + s * rng.standard_normal((1, P, 2, 2))
    a_cc, _ = linearised_rows(G, X, c)
    lin = linearised_disagreement(noisy, G, a_cc)
    green = project_strain(green_strain(noisy), X, c)[0] - project_strain(green_strain(G), X, c)[0]
    se = np.std(lin) / np.sqrt(P)
    assert abs(np.mean(lin)) < 4 * se
    assert abs(np.mean(green) - s ** 2) < 4 * se + 0.1 * s ** 2


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.001, 0.05), st.floats(0.0, 0.6))
def test_the_curve_noise_variance_recovers_white_noise_and_undercounts_correlated_noise_as_stated(seed, sd, rho):
    """On a smooth curve: white noise's variance recovered; AR(1) noise's undercounted by the stated factor
    (1.5 - 2 r1 + r2 / 2) / 1.5."""
    rng = np.random.default_rng(seed)
    F = 60
    curve = 0.2 * np.sin(np.linspace(0, np.pi, F))
    est = np.mean([curve_noise_variance(curve + _ar1(rng, F, rho, sd)) for _ in range(30)])
    factor = (1.5 - 2 * rho + 0.5 * rho ** 2) / 1.5
    # relative standard error of the mean of 30 (F - 2) squared second differences of white noise, whose
    # lag-1 and lag-2 correlations are -2/3 and 1/6 (AR(1) noise gives less); five of them, and the curve's
    # own roughness (tiny)
    se = np.sqrt(2 * (1 + 2 * ((2 / 3) ** 2 + (1 / 6) ** 2)) / (30 * (F - 2)))
    assert abs(est / (factor * sd ** 2) - 1) < 5 * se + (2e-4 / sd) ** 2
    with pytest.raises(ValueError, match="diff: expected 3 consecutive"):
        curve_noise_variance(np.array([0.1, np.nan, 0.2, np.nan]))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.001, 0.05))
def test_the_discrepancy_is_zero_when_the_estimate_agrees_with_the_reference_within_its_noise(seed, noise):
    """Only white noise between estimate and reference, its variance estimated from the curve itself: no
    excess (in the mean over draws, within a few standard errors of the squared-noise moment)."""
    rng = np.random.default_rng(seed)
    F = 60
    m = 0.2 * np.sin(np.linspace(0, np.pi, F))
    tau2 = []
    for _ in range(20):
        d = noise * rng.standard_normal(F)
        tau0_2, k2, j2 = discrepancy_variance(d, m, curve_noise_variance(d))
        tau2.append(tau0_2 + k2 * np.mean(m ** 2) + j2 * np.mean(curve_curvature(m) ** 2))
    assert np.mean(tau2) < 4 * noise ** 2 * np.sqrt(2 / F)
    assert discrepancy_variance(np.zeros(F), m, 0.0) == (0.0, 0.0, 0.0)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.05, 0.5), st.booleans(), st.floats(0.002, 0.01))
def test_a_known_discrepancy_is_recovered_through_known_noise_with_its_profile(seed, kappa, proportional, noise):
    """A bias proportional to the estimate (a flattening) or a constant offset, seen through white noise whose
    variance is given: its mean square recovered, and the profile told apart."""
    rng = np.random.default_rng(seed)
    F = 60
    m = 0.3 * np.sin(np.linspace(0, np.pi, F)) ** 2
    bias = kappa * m if proportional else np.full(F, 0.1 * kappa)
    est = []
    for _ in range(10):
        est.append(discrepancy_variance(bias + noise * rng.standard_normal(F), m, noise ** 2, curvature=False))
    tau0_2, k2, j2 = np.mean(est, axis=0)
    assert j2 == 0.0
    tau2 = tau0_2 + k2 * m ** 2
    slack = 4 * noise * np.sqrt(np.mean(bias ** 2)) / np.sqrt(10 * F) * 3 + 4 * noise ** 2 * np.sqrt(2 / (10 * F))
    assert abs(np.mean(tau2) - np.mean(bias ** 2)) < 0.1 * np.mean(bias ** 2) + slack
    if proportional:                      # where the estimate is zero, so is a proportional bias's variance
        assert tau0_2 < 0.1 * np.max(bias ** 2) + slack
    else:
        assert k2 * np.max(m ** 2) < 0.1 * np.max(bias ** 2) + slack


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.floats(2.0, 8.0), st.floats(0.0005, 0.003))
def test_a_smoothers_bias_at_the_onset_is_seen_by_the_bend_term(seed, width, noise):
    """A contraction that starts at a kink, smoothed by a Gaussian of ``width`` frames: the smoothed
    curve leads the onset and rounds the peak, an error largest where the curve bends, not where it
    is large. The bend term takes most of that excess, and the fitted variance covers the bias at the
    onset, where the two-term rule (the strain's value alone) leaves it uncovered."""
    rng = np.random.default_rng(seed)
    F = 60
    t = np.arange(F, dtype=float)
    truth = 0.4 * np.clip((t - 15) / 20, 0, 1) ** 2 * np.exp(-np.clip(t - 35, 0, None) / 10)
    m = gaussian_filter1d(truth, width, mode="nearest")             # the smoother's estimate
    bias = m - truth
    d = -bias + noise * rng.standard_normal(F)                         # reference (truth + noise) - estimate
    tau0_2, k2, j2 = discrepancy_variance(d, m, noise ** 2)
    assert j2 > 0
    onset = slice(8, 18)
    var3 = tau0_2 + k2 * m ** 2 + j2 * curve_curvature(m) ** 2
    t0, k, _ = discrepancy_variance(d, m, noise ** 2, curvature=False)
    var2 = t0 + k * m ** 2
    covered3 = np.mean(np.abs(bias[onset]) <= 1.96 * np.sqrt(var3[onset] + 1e-30))
    covered2 = np.mean(np.abs(bias[onset]) <= 1.96 * np.sqrt(var2[onset] + 1e-30))
    assert covered3 >= covered2
    # the moments d_t^2 - noise^2 have variance 4 b_t^2 noise^2 + 2 noise^4: a few standard errors of their mean
    se = np.sqrt((4 * np.mean(bias ** 2) * noise ** 2 + 2 * noise ** 4) / F)
    assert abs(np.mean(var3) - np.mean(bias ** 2)) <= 0.5 * np.mean(bias ** 2) + 6 * se


def test_the_bend_is_the_second_difference_with_its_ends_copied():
    m = np.array([0.0, 1.0, 4.0, 9.0, 16.0])                           # t^2: second difference 2 everywhere
    assert np.allclose(curve_curvature(m), 2.0)
    assert np.allclose(curve_curvature(np.column_stack([m, -m])), [[2.0, -2.0]] * 5)
    assert np.allclose(curve_curvature(np.array([0.3, 0.5])), 0.0)     # under 3 frames: no bend to see
    assert np.isnan(curve_curvature(np.array([0.0, np.nan, 1.0, 2.0, 3.0]))[[0, 1, 2]]).all()
    with pytest.raises(ValueError, match="curve: expected"):
        curve_curvature(np.zeros((3, 2, 2)))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000), st.integers(3, 12), st.integers(1, 5))
def test_the_excess_variance_takes_each_curves_bend_over_the_frames(seed, F, k):
    rng = np.random.default_rng(seed)
    m = rng.normal(size=(F, k))
    tau = rng.uniform(0, 1, size=(k, 3))
    c = np.empty_like(m)
    c[1:-1] = m[2:] - 2 * m[1:-1] + m[:-2]
    c[0], c[-1] = c[1], c[-2]
    want = tau[:, 0] + tau[:, 1] * m ** 2 + tau[:, 2] * c ** 2
    assert np.allclose(excess_variance(tau, m), want)
    assert np.allclose(excess_variance(tau[0], m[:, 0]), want[:, 0])


def test_the_excess_variance_refuses_bad_parameters():
    with pytest.raises(ValueError, match="tau: expected"):
        excess_variance(np.ones((2, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="tau: expected non-negative"):
        excess_variance(np.array([0.1, -0.1, 0.0]), np.zeros(5))


def test_curve_discrepancy_shares_one_model_over_the_segments_and_finds_the_global_curve_apart():
    rng = np.random.default_rng(5)
    F, S = 50, 6
    m = np.tile(0.2 * np.sin(np.linspace(0, np.pi, F))[:, None], (1, 1 + S))
    d = 0.002 * rng.standard_normal((F, 1 + S))
    d[:, 1:] += 0.3 * m[:, 1:]                          # the segments flattened by 30%, the global curve not
    tau = curve_discrepancy(d, m, curvature=False)
    assert np.allclose(tau[1:], tau[1])
    assert np.sqrt(tau[1, 1]) == pytest.approx(0.3, rel=0.1)
    assert tau[0, 0] + tau[0, 1] * np.mean(m[:, 0] ** 2) < 0.1 * tau[1, 1] * np.mean(m[:, 1] ** 2)


def test_curve_discrepancy_leaves_the_estimates_own_share_of_the_noise_in_the_excess():
    """An estimate made from the same data follows part of their noise: ``reference - estimate`` keeps
    the reference's noise less the estimate's own variance (the smoothed residual's ``R - H P H^T``).
    Given the estimate's sd, the constant bias is found; without it, it is understated by that variance."""
    rng = np.random.default_rng(3)
    F, S, h, b = 4000, 6, 5, 0.7                           # frames, segments, smoother width, bias
    n = rng.standard_normal((F + h - 1, 1 + S))             # the reference's white noise, variance 1
    e = np.stack([np.convolve(n[:, g], np.ones(h) / h, mode="valid") for g in range(1 + S)], axis=1)
    n = n[h // 2:F + h // 2]                                # the noise of frame t, centred in e's window
    d = n - (b + e)                                         # reference - estimate: estimate = truth + b + e
    m = np.zeros((F, 1 + S))                                # no relative or bend part to find
    own_sd = np.full((F, 1 + S), np.sqrt(1.0 / h))          # the smoother's sd: var(e) = 1 / h
    with_own = curve_discrepancy(d, m, curvature=False, model_sd=own_sd)
    without = curve_discrepancy(d, m, curvature=False)
    assert with_own[:, 0] == pytest.approx(b ** 2, rel=0.15)
    assert without[:, 0] == pytest.approx(b ** 2 - 1.0 / h, rel=0.2)
    with pytest.raises(ValueError, match="model_sd: expected shape"):
        curve_discrepancy(d, m, model_sd=own_sd[:, :3])


def test_discrepancy_errors_name_the_argument():
    with pytest.raises(ValueError, match="estimate: expected shape"):
        discrepancy_variance(np.zeros(5), np.zeros(4), 0.0)
    with pytest.raises(ValueError, match="at least 2 frames"):
        discrepancy_variance(np.array([0.0, np.nan]), np.zeros(2), 0.0)
    with pytest.raises(ValueError, match="noise_var: expected non-negative"):
        discrepancy_variance(np.zeros(3), np.zeros(3), -1.0)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.1, 50.0))
def test_the_ml_noise_scale_recovers_the_factor_the_model_missed(seed, c0):
    rng = np.random.default_rng(seed)
    F, m = 40, 6
    nis = np.empty(F)
    for t in range(F):
        L = rng.standard_normal((m, m))
        S = L @ L.T + m * np.eye(m)
        e = np.linalg.cholesky(c0 * S) @ rng.standard_normal(m)
        nis[t] = e @ np.linalg.solve(S, e)
    c = noise_scale(nis, np.full(F, m))
    assert abs(c / c0 - 1) < 4 * np.sqrt(2 / (F * m))                     # chi-square: sd of the mean NIS
    with pytest.raises(ValueError, match="nis, n_obs"):
        noise_scale(np.full(3, np.nan), np.zeros(3))


def test_the_scaled_bands_of_a_gaussian_local_level_model_cover_at_their_nominal_rate():
    """A random walk seen in white noise, filtered with both variances c0 = 9 times too small: the
    filter's own 95% bands cover a third of the truth; scaled by the ML noise scale, 95%."""
    rng = np.random.default_rng(7)
    series, F, q, r, c0 = 200, 60, 0.1, 1.0, 9.0
    inside_raw, inside_ml, n = 0, 0, 0
    for _ in range(series):
        x = np.cumsum(np.sqrt(c0 * q) * rng.standard_normal(F))
        y = x + np.sqrt(c0 * r) * rng.standard_normal(F)
        m, P, nis, est, var = 0.0, 1e6, [], [], []
        for t in range(F):
            P = P + q if t else P
            S = P + r
            e = y[t] - m
            if t:
                nis.append(e * e / S)
            K = P / S
            m, P = m + K * e, (1 - K) * P
            est.append(m)
            var.append(P)
        c = noise_scale(np.array(nis), np.ones(len(nis)))
        est, var = np.array(est)[5:], np.array(var)[5:]
        inside_raw += np.sum(np.abs(est - x[5:]) <= 1.96 * np.sqrt(var))
        inside_ml += np.sum(np.abs(est - x[5:]) <= 1.96 * np.sqrt(c * var))
        n += est.size
    assert inside_raw / n < 0.6
    assert 0.93 <= inside_ml / n <= 0.97


def test_dense_strain_keeps_the_smoothers_sd_beside_the_total_and_the_switches_work():
    tracks = thickening_ring_tracks(MASK, turn=0.0)[0]
    full = dense_strain(tracks, MASK, PX, StrainRouteSettings(element_px=2.0))
    bare = dense_strain(tracks, MASK, PX, StrainRouteSettings(element_px=2.0, noise_scale=False, discrepancy=False))
    for q in ("Ecc", "Err"):
        assert np.all(getattr(full, f"{q}_sd") >= getattr(full, f"{q}_sd_model") - 1e-15)
        assert np.all(full.segment_curves[f"{q}_sd"] >= full.segment_curves[f"{q}_sd_model"] - 1e-15)
        assert np.array_equal(getattr(bare, f"{q}_sd"), getattr(bare, f"{q}_sd_model"))
        assert np.allclose(getattr(full, q), getattr(bare, q))             # the bands change, the estimate not
        c = full.settings["noise_scale_ml"]
        assert np.allclose(full.segment_curves[f"{q}_sd_model"], np.sqrt(c) * bare.segment_curves[f"{q}_sd"])
        lo, hi = full.band(q, "pixels")
        assert np.allclose(hi - lo, 2 * 1.959963984540054 * getattr(full, f"{q}_sd"))
    assert bare.settings["noise_scale_ml"] == 1.0
    # the reference the excess was measured against: the tracks' finite-difference strain, linearised at the
    # estimate, i.e. the Green strain of the finite differences less the mean of |(G_fd - G) e|^2 / 2 >= 0
    E_fd = dict(zip(("Ecc", "Err", "Ecr"), project_strain(green_strain(displacement_gradient(full.points,
                                                                                           tracks.displacement)),
                                                          full.points, full.centre)))
    for q in ("Ecc", "Err"):
        assert np.array_equal(full.segment_curves[f"{q}_reference"], bare.segment_curves[f"{q}_reference"])
        assert full.segment_curves[f"{q}_reference"].shape == full.segment_curves[q].shape
        fd = segment_curves(E_fd[q], full.labels)
        below = fd - full.segment_curves[f"{q}_reference"]
        assert np.all(below >= -1e-12)
        assert np.mean(below) < np.mean(np.abs(full.segment_curves[q] - fd))
    # the total is the smoother's variance plus tau0^2 + k^2 m^2 + j^2 c^2, c the second difference over the
    # frames (the ends copied), with each curve's own parameters, and each pixel its segment's with its own m, c
    def bend(m):                                                       # frames along axis 0
        c = np.empty_like(m)
        c[1:-1] = m[2:] - 2 * m[1:-1] + m[:-2]
        c[0], c[-1] = c[1], c[-2]
        return c
    for q in ("Ecc", "Err"):
        disc = full.settings["discrepancy_sd"][q]
        t0, k, j = np.asarray(disc["segments"]).T[:, :, None]          # each (6, 1)
        m = full.segment_curves[q]
        want = full.segment_curves[f"{q}_sd_model"] ** 2 + t0 ** 2 + k ** 2 * m ** 2 + j ** 2 * bend(m.T).T ** 2
        assert np.allclose(full.segment_curves[f"{q}_sd"] ** 2, want, rtol=1e-10, atol=1e-16)
        g0, gk, gj = disc["global"]
        mg = full.global_curves[q]
        want = full.global_curves[f"{q}_sd_model"] ** 2 + g0 ** 2 + gk ** 2 * mg ** 2 + gj ** 2 * bend(mg) ** 2
        assert np.allclose(full.global_curves[f"{q}_sd"] ** 2, want, rtol=1e-10, atol=1e-16)
        P0, Pk, Pj = (v[full.labels][None, :] for v in np.asarray(disc["segments"]).T)
        mp = getattr(full, q)
        want = getattr(full, f"{q}_sd_model") ** 2 + P0 ** 2 + Pk ** 2 * mp ** 2 + Pj ** 2 * bend(mp) ** 2
        assert np.allclose(getattr(full, f"{q}_sd") ** 2, want, rtol=1e-10, atol=1e-16)
    assert max(np.max(np.asarray(full.settings["discrepancy_sd"][q]["segments"])[:, 2]) for q in ("Ecc", "Err")) > 0
    d = full.to_dict()
    assert {"Ecc_sd_model", "Err_sd_model"} <= set(d["strain"])
    with pytest.raises(ValueError, match="strain: expected one of"):
        StrainRouteSettings(strain="quadratic")
    with pytest.raises(TypeError, match="discrepancy: expected True or False"):
        StrainRouteSettings(discrepancy="yes")


def test_gradient_operators_reject_an_unknown_kind():
    with pytest.raises(ValueError, match="kind: expected one of"):
        gradient_operators(MESH, POINTS, "spline")
    assert isinstance(gradient_operators(MESH, POINTS)[1], sp.csr_matrix)


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 10_000), st.floats(0.05, 20.0))
def test_the_concentrated_evidence_is_the_likelihood_maximised_over_the_common_noise_scale(seed, c0):
    """``log p(y | c)`` of Gaussian innovations with covariances ``c S_t``: the closed form equals its maximum
    over a fine grid of ``c`` (never below any grid value) and the maximiser is the mean NIS."""
    rng = np.random.default_rng(seed)
    F, m = 12, 3
    S = [np.eye(m) * rng.uniform(0.5, 2.0) for _ in range(F)]
    e = [np.sqrt(c0) * np.linalg.cholesky(St) @ rng.standard_normal(m) for St in S]
    nis = np.array([ei @ np.linalg.solve(St, ei) for ei, St in zip(e, S)])
    logdet = sum(np.linalg.slogdet(St)[1] for St in S)

    def ll(c):
        return -0.5 * (logdet + F * m * np.log(c) + nis.sum() / c + F * m * np.log(2 * np.pi))

    ev, c_hat = concentrated_log_evidence(ll(1.0), nis.sum(), F * m)
    assert c_hat == pytest.approx(nis.sum() / (F * m))
    assert ev == pytest.approx(ll(c_hat), rel=1e-12, abs=1e-9)
    grid = c_hat * np.exp(np.linspace(-2, 2, 81))
    assert all(ev >= ll(c) - 1e-9 for c in grid)
    with pytest.raises(ValueError, match="nis_sum, n_obs"):
        concentrated_log_evidence(0.0, 0.0, 3)


def _moving_ring(rough: bool, frames=16, noise_px=0.03, seed=2):
    """Tracks of a ring contracting smoothly, or with a random-walk jitter of its radial motion."""
    X = reference_points(MASK)
    c = X.mean(axis=0)
    d = X - c
    r = np.linalg.norm(d, axis=1)
    rng = np.random.default_rng(seed)
    amp = 0.5 * np.sin(np.linspace(0.1, np.pi, frames))
    if rough:
        amp = amp + np.cumsum(0.25 * rng.standard_normal(frames))
    disp = -amp[:, None, None] * (8.0 / r)[None, :, None] * (d / r[:, None])[None]
    return LagrangianDisplacement(points=X, displacement=disp + noise_px * rng.standard_normal(disp.shape),
                                  sd=np.full(disp.shape, noise_px), confidence=np.ones(disp.shape[:2]),
                                  frame_times_s=0.0225 + 0.015 * np.arange(frames), n_untracked=0,
                                  noise_sd=np.array([1.0, 1.0]))


def test_the_evidence_asks_for_more_process_noise_where_the_motion_is_rougher():
    """The same noise, a smooth and a jittery motion: the evidence's process fraction is larger for the latter,
    and the route reports the candidates' evidence and uses its choice."""
    cfg = StrainRouteSettings(element_px=2.0, process_fraction=None, process_profile="constant")   # one level
    q_smooth, t_smooth = process_fraction_ml(MESH, _moving_ring(False), PX, cfg)
    q_rough, t_rough = process_fraction_ml(MESH, _moving_ring(True), PX, cfg)
    assert q_rough > q_smooth
    assert set(t_smooth) == set(PROCESS_FRACTIONS)
    assert min(PROCESS_FRACTIONS) <= q_smooth <= max(PROCESS_FRACTIONS)
    r = dense_strain(_moving_ring(True), MASK, PX, cfg)
    assert r.settings["process_fraction"] == pytest.approx(q_rough)
    assert set(r.settings["process_fraction_evidence"]) == {f"{q:g}" for q in PROCESS_FRACTIONS}
    fixed = dense_strain(_moving_ring(True), MASK, PX, StrainRouteSettings(element_px=2.0, process_profile="constant"))
    assert fixed.settings["process_fraction"] == 0.1                    # the default: the measured-data rule
    assert fixed.settings["process_fraction_evidence"] == "fixed by the settings"
