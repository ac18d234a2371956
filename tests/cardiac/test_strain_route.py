"""The DENSE route: Green strain of the FE field, its linearised sd, curves with full-covariance bands."""
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gmsh", reason="gmsh (the optional mesher, GPL-2.0-or-later) is not installed")

from hypothesis import example, given  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from sfem_filters.cardiac.strain_route import (  # noqa: E402
    NIS_EXCESS_MIN_S,
    StrainRouteSettings,
    _curve_rows,
    _element_of,
    dense_strain,
    element_gradient_operator,
    linearised_rows,
    nis_excess_min_frames,
    reference_mesh,
    strain_and_sd,
)
from helpers import thickening_ring_tracks  # noqa: E402
from sfem_filters.cardiac.annulus import annulus_mask  # noqa: E402
from sfem_filters.imaging.dense import reference_points  # noqa: E402
from sfem_filters.imaging.strain import green_strain, mask_centre, project_strain, segment_labels  # noqa: E402

PX = 1.75e-3


def _setup(element_px=2.0):
    mask = annulus_mask(4.0, 8.5, 24)
    mesh = reference_mesh(mask, PX, "gmsh", element_px)
    X = reference_points(mask)
    elem = _element_of(mesh, X * PX)
    return mask, mesh, X, elem, element_gradient_operator(mesh)


def _gradients(Ge, elem, mesh, U):
    """(..., P, 2, 2) element gradients at the points for nodal displacements U (..., n_dofs)."""
    Ue = U[..., mesh.element_dofs[elem]]                       # (..., P, 6)
    return np.einsum("pkd,...pd->...pk", Ge[elem], Ue).reshape(U.shape[:-1] + (len(elem), 2, 2))


def test_the_element_gradient_of_an_affine_field_is_exact_and_a_rigid_rotation_has_no_green_strain():
    mask, mesh, X, elem, Ge = _setup()
    A = np.array([[0.1, -0.3], [0.25, 0.05]])
    U = (mesh.nodes @ A.T).ravel()
    g = _gradients(Ge, elem, mesh, U)
    assert np.allclose(g, A, atol=1e-12)
    a = np.radians(35.0)
    Rm = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    U = (mesh.nodes @ (Rm - np.eye(2)).T + [1e-3, -2e-3]).ravel()
    g = _gradients(Ge, elem, mesh, U)
    assert np.max(np.abs(green_strain(g))) < 1e-12
    assert np.max(np.abs(0.5 * (g + np.swapaxes(g, -1, -2)))) > 0.1      # the small strain is not rotation-free


def _random_state(mesh, rng, sd=2e-6):
    """A deformed mean (10% radial dilation, a twist) and a random SPD covariance of the dofs (m^2)."""
    c = mesh.nodes.mean(axis=0)
    d = mesh.nodes - c
    U = (0.1 * d + 0.05 * np.column_stack([-d[:, 1], d[:, 0]])).ravel()
    n = mesh.n_dofs
    L = rng.standard_normal((n, n)) / np.sqrt(n)
    C = sd ** 2 * (L @ L.T + 0.2 * np.eye(n))
    dilation = 0.005 * d.ravel()                                   # a smooth mode (0.5% dilation sd), as a
    C += np.outer(dilation, dilation)                              # posterior has: correlated strain
    return U, C


def test_the_linearised_strain_sd_matches_a_monte_carlo_of_displacement_draws():
    mask, mesh, X, elem, Ge = _setup()
    rng = np.random.default_rng(0)
    U, C = _random_state(mesh, rng)
    centre = mask_centre(mask)
    g0 = _gradients(Ge, elem, mesh, U)
    # the 4 x 4 covariance of each point's gradient, B C B^T
    B = np.zeros((len(elem), 4, mesh.n_dofs))
    for p, e in enumerate(elem):
        B[p][:, mesh.element_dofs[e]] = Ge[e]
    cov = np.einsum("pid,de,pje->pij", B, C, B)
    _, _, _, sd_cc, sd_rr = strain_and_sd(g0, cov, X, centre)
    draws = rng.multivariate_normal(U, C, size=4000)
    ecc, err, _ = project_strain(green_strain(_gradients(Ge, elem, mesh, draws)), X, centre)
    mc_cc, mc_rr = ecc.std(axis=0), err.std(axis=0)
    # 4000 draws: the sd of an sd estimate is ~1.1%; the linearisation error is second order
    assert np.allclose(sd_cc, mc_cc, rtol=0.06)
    assert np.allclose(sd_rr, mc_rr, rtol=0.06)
    # the delta method's F matters: the small-strain sd (F = I) is off by more than the tolerance
    _, _, _, sd_small, _ = strain_and_sd(np.zeros_like(g0), cov, X, centre)
    assert np.max(np.abs(sd_small / mc_cc - 1)) > 0.06


def test_the_segment_band_is_the_sd_of_the_mean_from_the_full_covariance():
    mask, mesh, X, elem, Ge = _setup()
    rng = np.random.default_rng(1)
    U, C = _random_state(mesh, rng)
    centre = mask_centre(mask)
    g0 = _gradients(Ge, elem, mesh, U)
    a_cc, _ = linearised_rows(g0, X, centre)
    labels = segment_labels(X, centre, 30.0)
    groups = [np.arange(len(X))] + [np.flatnonzero(labels == k) for k in range(6)]
    rows = _curve_rows(Ge, elem, a_cc, groups, mesh.n_dofs, mesh.element_dofs)
    var_rows = np.einsum("gi,ij,gj->g", rows, C, rows)
    # by hand: the (P, n_dofs) Jacobian of every point's Ecc, then w^T (A C A^T) w for each group
    A = np.zeros((len(X), mesh.n_dofs))
    for p, e in enumerate(elem):
        for k in range(4):
            A[p, mesh.element_dofs[e]] += a_cc[p, k] * Ge[e, k]
    cov_points = A @ C @ A.T
    for g, sel in enumerate(groups):
        w = np.zeros(len(X))
        w[sel] = 1.0 / sel.size
        assert var_rows[g] == pytest.approx(w @ cov_points @ w, rel=1e-10)
        independent = np.sum(np.diag(cov_points)[sel]) / sel.size ** 2
        assert abs(var_rows[g] - independent) > 0.05 * var_rows[g]      # the correlations count


def test_dense_strain_on_a_small_ring_gives_the_issue_names_and_honest_shapes():
    mask = annulus_mask(4.0, 8.5, 24)
    tracks, truth = thickening_ring_tracks(mask)
    messages = []
    r = dense_strain(tracks, mask, PX, StrainRouteSettings(element_px=2.0, start_deg=15.0), progress=messages.append)
    F, P = tracks.displacement.shape[:2]
    assert messages and "meshing" in messages[0]
    for name in ("Ecc", "Err", "Ecr", "Ecc_sd", "Err_sd"):
        assert getattr(r, name).shape == (F, P) and np.all(np.isfinite(getattr(r, name)))
    assert np.all(r.Ecc_sd > 0) and np.all(r.Err_sd > 0)
    for q in ("Ecc", "Err"):
        assert r.global_curves[q].shape == (F,) and r.segment_curves[q].shape == (6, F)
        lo, hi = r.band(q)
        assert np.all(lo < r.segment_curves[q]) and np.all(r.segment_curves[q] < hi)
        # a mean of correlated pixels is less sure than the pixels' own sd over sqrt(n) would say ... but
        # never less sure than the least sure pixel
        assert np.all(r.global_curves[f"{q}_sd"] <= getattr(r, f"{q}_sd").max(axis=1) + 1e-12)
    d = r.to_dict()
    assert set(d) >= {"points", "frame_times_s", "strain", "global", "segments", "seconds", "route", "settings"}
    assert set(d["strain"]) == {"Ecc", "Err", "Ecr", "Ecc_sd", "Err_sd", "Ecc_sd_model", "Err_sd_model"}
    assert set(d["global"]) >= {"Ecc", "Err", "Ecc_lo", "Ecc_hi", "Err_lo", "Err_hi"}
    assert d["segments"]["start_deg"] == 15.0 and np.shape(d["segments"]["Err_hi"]) == (6, F)
    # the truth's strain (exact Green strain of u, by central differences of the field) is recovered in the mean
    c = mask_centre(mask)
    k = 0.15 * np.linspace(0.2, 1.0, F) * 20.0
    h = 1e-5

    def u_at(x, kk, tt):
        d = x - c
        rr = np.linalg.norm(d, axis=-1, keepdims=True)
        return -kk * d / rr ** 2 + 0.02 * tt * np.stack([-d[..., 1], d[..., 0]], axis=-1)

    for f, (kk, tt) in enumerate(zip(k, np.linspace(0.2, 1.0, F))):
        G = np.stack([(u_at(tracks.points + [h, 0], kk, tt) - u_at(tracks.points - [h, 0], kk, tt)) / (2 * h),
                      (u_at(tracks.points + [0, h], kk, tt) - u_at(tracks.points - [0, h], kk, tt)) / (2 * h)], axis=-1)
        ecc, err, _ = project_strain(green_strain(G), tracks.points, c)
        assert abs(r.global_curves["Err"][f] - err.mean()) < 0.01 + 0.2 * abs(err.mean())
        assert abs(r.global_curves["Ecc"][f] - ecc.mean()) < 0.01 + 0.2 * abs(ecc.mean())
    assert err.mean() > 0.05 and ecc.mean() < -0.05                      # the wall thickens, the ring shortens


def test_the_one_pass_estimate_is_the_iterated_smoothers_map():
    """The route runs one forward pass for its means and covariances (the material is fixed, the model
    linear); its displacement must be the iterated smoother's MAP trajectory of the same model."""
    from sfem_filters.cardiac.dense_model import build_dense_model
    from sfem_filters.fem.observation import point_observation_matrix
    from sfem_filters.filtering.iterated import IteratedSmoother

    mask = annulus_mask(4.0, 8.5, 24)
    tracks, _ = thickening_ring_tracks(mask)
    cfg = StrainRouteSettings(element_px=2.0, effects=("cavity_pressure",))      # an effect adds a state
    r = dense_strain(tracks, mask, PX, cfg)
    mesh = reference_mesh(mask, PX, cfg.mesh, cfg.element_px)
    model, y, _, Xin = build_dense_model(mesh, tracks, PX, cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)             # the NIS monitor's, as in the route
        states = IteratedSmoother(covariance=False).run(model, y).states
    U = np.zeros((len(y), mesh.n_dofs))
    U[:, model.dofmap.free] = states[:, :model.dim_x // 2]
    disp = (point_observation_matrix(mesh, Xin) @ U.T).T.reshape(r.displacement.shape) / PX
    assert np.max(np.abs(disp - r.displacement)) <= 1e-7 * np.max(np.abs(r.displacement))   # round-off
    assert np.max(np.abs(r.displacement)) > 0.1                           # the ring moves (px)


DATA = Path(os.environ.get("SFEM_FILTERS_DATA", Path(__file__).resolve().parents[3] / "shared" / "data"))
CASE = DATA / "dense_sim" / "phantom_subject_1"


@pytest.mark.skipif(not (CASE / "config.yaml").is_file(),
                    reason=f"the DENSE-Sim case is not here ({CASE}); set SFEM_FILTERS_DATA to the shared data")
def test_on_the_given_phantom_the_first_frames_follow_the_truth():
    from sfem_filters.imaging.dense import add_complex_noise, make_dense_case, phase_to_displacement, read_dense_sim
    from sfem_filters.imaging.dense import truth_at_points
    full = read_dense_sim(CASE)
    k = 8                                                         # the first 8 frames: a quick check
    case = make_dense_case(full.phases[:, :k], full.magnitude[:k], full.masks[:k + 1], full.pixel_size_mm, 0.1,
                           full.frame_times_s[:k], truth_ecc=full.truth_ecc[:k], truth_err=full.truth_err[:k])
    noisy = add_complex_noise(case, 30.0, 0)
    r = dense_strain(phase_to_displacement(noisy), noisy.reference_mask, noisy.pixel_size_m)
    te, tr = truth_at_points(noisy)
    # the global curves within 2 points of the truth's over these early frames
    assert np.max(np.abs(r.global_curves["Ecc"] - np.nanmean(te, axis=1))) < 0.02
    assert np.max(np.abs(r.global_curves["Err"] - np.nanmean(tr, axis=1))) < 0.02


def test_frames_where_the_data_outrun_the_model_are_named_once_and_kept_in_the_settings():
    """A ring that thickens smoothly: no frame is flagged. The same ring shaken across the wall at frames 4-11
    (half a pixel back and forth, faster than the model's motion can follow): one warning naming those frames
    and their times, the same frames in the settings, and the NIS per row that shows it."""
    from dataclasses import replace
    mask = annulus_mask(4.0, 8.5, 24)
    tracks, _ = thickening_ring_tracks(mask, frames=16)
    cfg = StrainRouteSettings(element_px=2.0, process_profile="constant")
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        r = dense_strain(tracks, mask, PX, cfg)
    assert r.settings["nis_excess_frames"] == [] and not [w for w in seen if "faster than" in str(w.message)]
    d = tracks.points - tracks.points.mean(axis=0)
    rr = np.linalg.norm(d, axis=1)
    shake = np.zeros(16)
    shake[4:12] = 0.5 * (-1.0) ** np.arange(8)
    shaken = replace(tracks, displacement=tracks.displacement - shake[:, None, None] * (d / rr[:, None])[None])
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        r = dense_strain(shaken, mask, PX, cfg)
    runs = r.settings["nis_excess_frames"]
    assert r.settings["nis_excess_min_frames"] == 4                   # 60 ms at these 15 ms frames
    assert len(runs) == 1 and 4 <= runs[0][0] <= 6 and runs[0][1] == 11
    hits = [w for w in seen if "faster than the model's motion" in str(w.message)]
    msgs = [str(w.message) for w in hits]
    assert len(msgs) == 1 and f"frames {runs[0][0]}-11 (" in msgs[0]
    assert f"-{1e3 * r.frame_times_s[11]:.0f} ms)" in msgs[0] and "4 frames or more in a row, 60 ms" in msgs[0]
    assert hits[0].filename == __file__                       # it points at the caller's line, not the library's
    nis = np.array(r.settings["nis_per_row"]) / r.settings["noise_scale_ml"]
    assert np.all(nis[runs[0][0]:12] > 1.0) and np.all(nis[12:] < 1.0)


@given(st.floats(0.002, 0.2))
@example(0.019999999996)                       # within the rounding's slack of 60 ms / 3
def test_the_run_that_names_a_lag_spans_the_same_time_at_any_frame_rate(interval):
    """The run that names a lag spans at least NIS_EXCESS_MIN_S (within the rounding's relative 1e-9) and is the
    shortest that does, never below 2 frames (one frame above a 99.9% bound is chance); 4 frames at DENSE-Sim's
    15 ms, 2 at 45 ms."""
    k = nis_excess_min_frames(interval)
    assert k >= 2 and (k * interval >= NIS_EXCESS_MIN_S * (1 - 1e-8) or k == 2)
    assert k == 2 or (k - 1) * interval < NIS_EXCESS_MIN_S
    assert nis_excess_min_frames(0.015) == 4 and nis_excess_min_frames(0.045) == 2


def test_a_short_lag_is_named_at_a_sparse_frame_rate_and_not_at_a_dense_one():
    """The ring shaken across the wall at frames 6-8 only: 45 ms at 15 ms frames, under the 60 ms a lag must last,
    so nothing is named; the same data at 45 ms frames (times x 3) last 135 ms, and frames 6-8 are named."""
    from dataclasses import replace
    mask = annulus_mask(4.0, 8.5, 24)
    tracks, _ = thickening_ring_tracks(mask, frames=16)
    cfg = StrainRouteSettings(element_px=2.0, process_profile="constant")
    d = tracks.points - tracks.points.mean(axis=0)
    shake = np.zeros(16)
    shake[6:9] = 0.5 * (-1.0) ** np.arange(3)
    shaken = replace(tracks, displacement=tracks.displacement
                     - shake[:, None, None] * (d / np.linalg.norm(d, axis=1)[:, None])[None])
    runs = {}
    for k in (1, 3):
        with warnings.catch_warnings(record=True):
            warnings.simplefilter("always")
            r = dense_strain(replace(shaken, frame_times_s=tracks.frame_times_s * k), mask, PX, cfg)
        runs[k] = (r.settings["nis_excess_min_frames"], r.settings["nis_excess_frames"])
    assert runs[1] == (4, []) and runs[3] == (2, [[6, 8]]), runs


@pytest.mark.parametrize("bad", [0.0, -0.015, float("nan")])
def test_the_lag_run_wants_a_positive_frame_interval(bad):
    with pytest.raises(ValueError, match="frame_interval_s"):
        nis_excess_min_frames(bad)


def test_a_stray_reference_pixel_is_not_observed_but_is_reported():
    """A pixel apart from the ring in the reference mask (mended away before meshing) carries a wild track: it is
    not observed, so the strain does not depend on its track at all, stays within a mesh change of the ring's
    alone, and the stray pixel gets the nearest tissue's strain, finite, with the count in the settings."""
    from sfem_filters.imaging.dense import LagrangianDisplacement
    mask = annulus_mask(4.0, 8.5, 24)
    tracks, _ = thickening_ring_tracks(mask)
    rows, cols = np.nonzero(mask)
    bigger = mask.copy()
    bigger[int(rows.max()), int(cols.max()) + 3] = True              # two empty pixels between it and the ring
    # the same centre for all (the spec's centre is the whole reference mask's, stray pixel included)
    cfg = StrainRouteSettings(element_px=2.0, centre=tuple(mask_centre(bigger)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        alone = dense_strain(tracks, mask, PX, cfg)
    X = reference_points(bigger)
    where = {tuple(p): i for i, p in enumerate(tracks.points.astype(int))}
    k = [where.get((int(x), int(y))) for x, y in X.astype(int)]
    s = int(np.flatnonzero([i is None for i in k])[0])
    idx = np.array([0 if i is None else i for i in k])

    def spread(a, fill):
        out = np.array(a, float)[:, idx]
        out[:, s] = fill
        return out

    runs = []
    for wild in (5.0, -3.0):
        t = LagrangianDisplacement(points=X, displacement=spread(tracks.displacement, wild),
                                   sd=spread(tracks.sd, 0.05), confidence=spread(tracks.confidence, 1.0),
                                   frame_times_s=tracks.frame_times_s, n_untracked=0, noise_sd=tracks.noise_sd)
        with warnings.catch_warnings(record=True) as seen:
            warnings.simplefilter("always")
            runs.append(dense_strain(t, bigger, PX, cfg))
        assert any("reference_mask: not one ring" in str(w.message) for w in seen)   # the mending's own warning
    r = runs[0]
    for q in ("Ecc", "Err", "Ecc_sd", "Err_sd"):
        np.testing.assert_allclose(getattr(runs[1], q), getattr(r, q), rtol=0, atol=1e-12)
    assert r.settings["reference_pixels_not_observed"] == 1 and alone.settings["reference_pixels_not_observed"] == 0
    assert r.settings["largest_move_px"] < 1.0                       # of the observed points: the stray is not one
    ring = np.delete(np.arange(len(X)), s)
    # the mesh of the mended mask is resampled from a border of one more pixel's count: a mesh change, no more
    assert np.max(np.abs(r.Err[:, ring] - alone.Err)) < 0.005 and np.max(np.abs(r.Ecc[:, ring] - alone.Ecc)) < 0.005
    assert np.all(np.isfinite(r.Err[:, s])) and np.all(np.isfinite(r.Err_sd[:, s]))


@pytest.mark.parametrize("times, match", [
    (lambda t: 1e3 * t, r"tracks.frame_times_s: expected seconds .* milliseconds\?"),
    (lambda t: t[::-1].copy(), r"tracks.frame_times_s: expected times \(s\) after the encoding, >= 0 and strictly"),
    (lambda t: np.where(np.arange(len(t)) == 2, t[1], t), r"strictly increasing"),
    (lambda t: t - 0.1, r">= 0"),
    (lambda t: np.where(np.arange(len(t)) == 2, np.nan, t), r"tracks.frame_times_s"),
])
def test_frame_times_that_are_not_seconds_after_the_encoding_are_named_before_any_pass(times, match):
    from dataclasses import replace
    mask = annulus_mask(4.0, 8.5, 24)
    tracks, _ = thickening_ring_tracks(mask, frames=6)
    with pytest.raises(ValueError, match=match):
        dense_strain(replace(tracks, frame_times_s=times(tracks.frame_times_s)), mask, PX)
