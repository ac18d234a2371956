"""The DENSE route fused with the myocardium masks (``border_masks=True``): shape tracking and phase data in one model.

Ground truth from an analytic deformation written here: a ring that thickens inwards keeping its area
(reference radius R of what is now at r: R^2 = r^2 + A_t), so the exact Green-Lagrange radial strain of a
reference pixel at radius R is ((R / r)^2 - 1) / 2 with r^2 = R^2 - A_t, and each frame's mask is exactly
the pixels whose reference radius lies in the wall. The phase tracks are made to lag at the endocardium (the
cavity's signal leaking into the first layers' phase, as in DENSE-Sim): the masks are not.
"""
import json
import re
import warnings
from dataclasses import asdict, replace

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

pytest.importorskip("gmsh", reason="gmsh (the optional mesher, GPL-2.0-or-later) is not installed")

from sfem_filters.cardiac.border_data import (QUANTISATION_SD_PX, contour_landmark_tracks,  # noqa: E402
                                              mask_border_data)
from sfem_filters.cardiac.dense_model import build_dense_model, phase_noise_level  # noqa: E402
from sfem_filters.cardiac.myocardium import lv_geometry  # noqa: E402
from sfem_filters.cardiac.strain_route import (StrainRouteSettings, border_masks_data, dense_strain,  # noqa: E402
                                               reference_mesh)
from sfem_filters.filtering.iterated import IteratedSmoother  # noqa: E402
from sfem_filters.filtering.linearised import linearise  # noqa: E402
from sfem_filters.filtering.smoother import kalman_forward  # noqa: E402
from sfem_filters.imaging import reference_mask_mismatch  # noqa: E402
from sfem_filters.imaging.dense import LagrangianDisplacement, reference_points  # noqa: E402

PX = 1.75e-3                                          # m
R_IN, R_OUT, SIZE = 7.5, 12.5, 32                     # px
CENTRE = np.array([15.3, 15.6])                       # px, off the pixel grid's symmetry
AREAS = 30.0 * np.sin(np.pi * np.arange(1, 9) / 9)    # px^2: the wall thickens to mid-cycle and relaxes


def _ring(lag=0.5, depth_px=1.5, noise_px=0.03, seed=0):
    """Reference mask, tracks lagging by ``lag`` at the endocardium (decaying over ``depth_px``), exact masks
    (F + 1, H, W), and the true Err (F, P)."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE].astype(float)
    r_px = np.hypot(xx - CENTRE[0], yy - CENTRE[1])
    ref = (r_px >= R_IN) & (r_px <= R_OUT)
    X = reference_points(ref)
    d = X - CENTRE
    R = np.linalg.norm(d, axis=1)
    disp, masks, err = [], [ref], []
    for A in AREAS:
        r = np.sqrt(R ** 2 - A)
        disp.append(((r - R) / R)[:, None] * d)
        Rp = np.sqrt(r_px ** 2 + A)
        masks.append((Rp >= R_IN) & (Rp <= R_OUT))
        err.append(0.5 * ((R / r) ** 2 - 1))
    disp = np.array(disp)
    biased = disp * (1 - lag * np.exp(-(R - R_IN) / depth_px))[None, :, None]
    rng = np.random.default_rng(seed)
    tracks = LagrangianDisplacement(points=X, displacement=biased + noise_px * rng.standard_normal(disp.shape),
                                    sd=np.full(disp.shape, noise_px), confidence=np.ones(disp.shape[:2]),
                                    frame_times_s=0.0225 + 0.015 * np.arange(len(AREAS)), n_untracked=0,
                                    noise_sd=np.array([1.0, 1.0]))
    return ref, tracks, np.stack(masks), np.array(err)


@pytest.fixture(scope="module")
def ring():
    return _ring()


def test_the_masks_pull_the_lagging_endocardium_back_to_the_true_thickening(ring):
    ref, tracks, masks, err = ring
    cfg = StrainRouteSettings(element_px=2.0, process_profile="constant")   # one process level: the fusion alone
    alone = dense_strain(tracks, ref, PX, cfg)
    fused = dense_strain(tracks, ref, PX, replace(cfg, border_masks=True), masks=masks)
    level = dense_strain(tracks, ref, PX, replace(cfg, border_masks=True, phase_noise_level="evidence"), masks=masks)
    truth = err.mean(axis=1)
    peak = int(np.argmax(truth))
    e = [r.global_curves["Err"][peak] - truth[peak] for r in (alone, fused, level)]
    rmse = [float(np.sqrt(np.mean((r.Err - err) ** 2))) for r in (alone, fused, level)]
    # the lagging tracks under-estimate the thickening; the masks' borders move as the wall does
    assert e[0] < -0.5 * truth[peak]
    # at the stated levels the phase data (many pixels, 0.03 px) outweigh the masks (0.29 px a border node):
    # closer, a little
    assert abs(e[1]) < abs(e[0]) and rmse[1] < rmse[0]
    # with the phase data at the level their innovations show (the bias is not white noise), the masks count
    assert level.settings["phase_noise_scale"] > 1
    assert abs(e[2]) < 0.8 * abs(e[1]) and rmse[2] < 0.8 * rmse[1]
    s = fused.settings
    assert s["border_masks"] is True and s["border_rows"] == s["border_nodes"] > 0
    assert s["border_sd_px_range"][0] >= QUANTISATION_SD_PX - 1e-12          # the contours route's sd rule
    json.dumps(fused.to_dict()["settings"])


def test_exact_tracks_and_exact_masks_agree_so_fusion_changes_little():
    ref, tracks, masks, err = _ring(lag=0.0)
    cfg = StrainRouteSettings(element_px=2.0)
    alone = dense_strain(tracks, ref, PX, cfg)
    fused = dense_strain(tracks, ref, PX, replace(cfg, border_masks=True), masks=masks)
    truth = err.mean(axis=1)
    peak = int(np.argmax(truth))
    assert abs(fused.global_curves["Err"][peak] - alone.global_curves["Err"][peak]) < 0.25 * truth[peak]


def test_the_border_rows_are_the_contours_routes_own_and_frames_alone_get_the_reference_prepended(ring):
    ref, tracks, masks, _ = ring
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    F = tracks.displacement.shape[0]
    a = border_masks_data(masks, ref, F, mesh, PX)
    b = border_masks_data(masks[1:], ref, F, mesh, PX)
    c = mask_border_data(mesh, contour_landmark_tracks(masks), PX)
    for x in (b, c):
        assert np.array_equal(a.nodes, x.nodes) and np.allclose(a.y, x.y) and np.allclose(a.R, x.R)
        assert (a.H != x.H).nnz == 0
    # stacked below the nodal fit: n_dofs + border rows, the border block of R the masks' own
    model, y, info, _ = build_dense_model(mesh, tracks, PX, StrainRouteSettings(element_px=2.0), border=a)
    n = mesh.n_dofs
    assert y.shape == (F, n + len(a.nodes)) and np.allclose(y[:, n:], a.y)
    assert np.allclose(model.R_at(3)[n:, n:], a.R[3]) and np.all(model.R_at(3)[:n, n:] == 0)
    assert info["border_rows"] == len(a.nodes)


def test_bad_masks_are_named(ring):
    ref, tracks, masks, _ = ring
    fused = StrainRouteSettings(element_px=2.0, border_masks=True)
    with pytest.raises(ValueError, match="masks: expected the myocardium masks"):
        dense_strain(tracks, ref, PX, fused)
    with pytest.raises(ValueError, match="masks: given, but settings.border_masks is False"):
        dense_strain(tracks, ref, PX, StrainRouteSettings(element_px=2.0), masks=masks)
    with pytest.raises(ValueError, match=r"masks: expected the myocardium masks of the 8 frames"):
        dense_strain(tracks, ref, PX, fused, masks=masks[:-2])
    with pytest.raises(ValueError, match=r"masks: expected the myocardium masks of the 8 frames"):
        dense_strain(tracks, ref, PX, fused, masks=masks[:, :-1])
    with pytest.raises(ValueError, match="masks: expected masks\\[0\\] to be the reference mask"):
        dense_strain(tracks, ref, PX, fused, masks=np.concatenate([masks[1:2], masks[1:]]))
    empty = masks.copy()
    empty[4] = False                       # one frame without myocardium: left out by the default, named
    with pytest.warns(RuntimeWarning, match=r"frame\(s\) \[3\] \(masks\[4\]\).*masks\[4\]: expected some tissue"):
        assert np.all(np.isfinite(dense_strain(tracks, ref, PX, fused, masks=empty).Err))
    with pytest.raises(ValueError, match=r"masks\[4\]: expected some tissue"):   # landmarks need every frame's
        dense_strain(tracks, ref, PX, replace(fused, border_correspondence="landmarks"), masks=empty)
    # the frames' masks alone, (F, H, W): the errors name the caller's index (the stack's is one more)
    with pytest.raises(ValueError, match=r"got masks\[3\] not \(masks\[3\]: expected some tissue"):
        dense_strain(tracks, ref, PX, replace(fused, border_correspondence="landmarks"), masks=empty[1:])
    empty[1:] = False
    with pytest.raises(ValueError, match=r"masks: expected myocardium in the frames' masks, got none in any"):
        dense_strain(tracks, ref, PX, fused, masks=empty)
    with pytest.raises(ValueError, match="masks: expected a boolean mask"):
        dense_strain(tracks, ref, PX, fused, masks=masks * 2)
    for junk in (True, 3.0):
        with pytest.raises(ValueError, match="masks: expected a 3D mask"):
            dense_strain(tracks, ref, PX, fused, masks=junk)
    with pytest.raises(TypeError, match="border_masks: expected True or False"):
        StrainRouteSettings(border_masks="yes")
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    b = border_masks_data(masks, ref, 8, mesh, PX)
    short = replace(b, y=b.y[:-1], R=b.R[:-1])
    with pytest.raises(ValueError, match="border: expected the data of F = 8 frames"):
        build_dense_model(mesh, tracks, PX, StrainRouteSettings(element_px=2.0), border=short)
    with pytest.raises(TypeError, match="border: expected a BorderData"):
        build_dense_model(mesh, tracks, PX, StrainRouteSettings(element_px=2.0), border=(b.H, b.y, b.R))


def test_the_settings_with_the_flag_survive_a_json_round_trip():
    cfg = StrainRouteSettings(border_masks=True, resolution_px=2.13, start_deg=30.0, centre=(15.3, 15.6))
    back = StrainRouteSettings(**json.loads(json.dumps(asdict(cfg))))
    assert back == cfg and back.border_masks is True
    assert StrainRouteSettings().border_masks is False


def test_a_common_phase_level_changes_no_estimate_and_scales_every_phase_covariance(ring):
    """``phase_scale`` multiplies R, Q and the initial covariance together (the phase data's own level,
    :func:`phase_noise_level`): alone it moves no estimate, beside the masks it shifts their weight."""
    ref, tracks, masks, _ = ring
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    cfg = StrainRouteSettings(element_px=2.0)
    m1, y1, _, _ = build_dense_model(mesh, tracks, PX, cfg)
    m9, y9, info, _ = build_dense_model(mesh, tracks, PX, cfg, phase_scale=9.0)
    assert info["phase_noise_scale"] == 9.0 and np.allclose(y1, y9)
    assert np.allclose(m9.R_at(2), 9 * m1.R_at(2)) and np.allclose(m9.Q, 9 * m1.Q) and np.allclose(m9.P0, 9 * m1.P0)
    x1 = IteratedSmoother(covariance=False).run(m1, y1).states
    x9 = IteratedSmoother(covariance=False).run(m9, y9).states
    assert np.allclose(x1, x9, rtol=1e-6, atol=1e-9 * np.abs(x1).max())
    b = border_masks_data(masks, ref, 8, mesh, PX)
    mb, yb, _, _ = build_dense_model(mesh, tracks, PX, cfg, border=b, phase_scale=9.0)
    n = mesh.n_dofs
    assert np.allclose(mb.R_at(2)[n:, n:], b.R[2]) and np.allclose(mb.R_at(2)[:n, :n], 9 * m1.R_at(2))


def test_the_phase_level_by_evidence_needs_the_masks_and_is_the_mean_nis_of_the_phase_alone(ring):
    ref, tracks, masks, _ = ring
    with pytest.raises(ValueError, match="phase_noise_level: 'evidence' weighs the phase data against the masks"):
        StrainRouteSettings(phase_noise_level="evidence")
    with pytest.raises(ValueError, match="phase_noise_level: expected one of"):
        StrainRouteSettings(border_masks=True, phase_noise_level="ml")
    cfg = StrainRouteSettings(element_px=2.0, border_masks=True, phase_noise_level="evidence")
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    c = phase_noise_level(mesh, tracks, PX, cfg)
    # the closed form is the level of largest evidence: the phase-only model at c has its mean NIS at one
    assert c > 0 and np.isfinite(c)
    model, y, _, _ = build_dense_model(mesh, tracks, PX, cfg, phase_scale=c)
    fw = kalman_forward(linearise(model, np.zeros((y.shape[0], model.dim_x))), y, store=False,
                        check_every_frame=False)
    assert np.nansum(fw.nis) / np.sum(fw.n_obs) == pytest.approx(1.0, rel=1e-6)
    r = dense_strain(tracks, ref, PX, cfg, masks=masks)
    assert r.settings["phase_noise_scale"] == pytest.approx(c)


def test_contours_start_where_asked_and_the_tracking_follows():
    from sfem_filters.imaging.contours import mask_borders
    ref = _ring()[0]
    for start in (0.0, 90.0, -45.0, 200.0):
        b = mask_borders(ref, 48, 64, start_deg=start)
        for c in (b.endo, b.epi):
            a = np.degrees(np.arctan2(c[0, 1] - b.centre[1], c[0, 0] - b.centre[0]))
            assert abs((a - start + 180) % 360 - 180) < 360 / len(c)          # within one point's spacing
    with pytest.raises(ValueError, match="start_deg"):
        mask_borders(ref, start_deg=float("nan"))
    masks = _ring()[2]
    t = contour_landmark_tracks(masks, start_deg=90.0)
    p0 = t.points[t.contour == 0][0] - t.borders[0].centre
    assert abs(np.degrees(np.arctan2(p0[1], p0[0])) - 90.0) < 10.0


def test_the_mean_over_contour_starts_depends_on_where_they_start_far_less_than_one_start_does(ring):
    """Eight starts 45 degrees apart against the same eight turned by 22.5 degrees: their means differ by a
    fraction of what two single starts 22.5 degrees apart do (the start's draw averages out)."""
    from sfem_filters.cardiac.border_data import mean_border_data
    ref, tracks, masks, _ = ring
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    one = {a: mask_border_data(mesh, contour_landmark_tracks(masks, start_deg=a), PX) for a in np.arange(16) * 22.5}
    even = mean_border_data([one[a] for a in np.arange(8) * 45.0])
    odd = mean_border_data([one[a] for a in np.arange(8) * 45.0 + 22.5])
    assert np.array_equal(even.nodes, odd.nodes) and even.y.shape == one[0.0].y.shape

    def rms(a, b):
        return float(np.sqrt(np.mean((a.y - b.y) ** 2)))

    single = np.mean([rms(one[a], one[a + 22.5]) for a in np.arange(8) * 45.0])
    assert single > 0 and rms(even, odd) < 0.5 * single
    # the mean's variance is the starts' mean variance (their errors share one staircase), not a eighth of it
    assert np.allclose(np.diagonal(even.R, axis1=1, axis2=2),
                       np.mean([np.diagonal(one[a].R, axis1=1, axis2=2) for a in np.arange(8) * 45.0], axis=0))
    # one BorderData is its own mean; tangential rows are refused
    same = mean_border_data([one[0.0]])
    assert np.array_equal(same.y, one[0.0].y) and (same.H != one[0.0].H).nnz == 0
    with pytest.raises(ValueError, match="normal data only"):
        mean_border_data([mask_border_data(mesh, contour_landmark_tracks(masks), PX, tangential=True)])
    with pytest.raises(TypeError, match="BorderData"):
        mean_border_data([])


def test_the_route_takes_border_starts_and_names_a_bad_value(ring):
    ref, tracks, masks, _ = ring
    cfg = StrainRouteSettings(element_px=2.0, border_masks=True, border_starts=4, border_correspondence="landmarks")
    r = dense_strain(tracks, ref, PX, cfg, masks=masks)
    assert r.settings["border_starts"] == 4 and np.all(np.isfinite(r.Err))
    one = dense_strain(tracks, ref, PX, replace(cfg, border_starts=1), masks=masks)
    assert not np.allclose(r.Err, one.Err)                     # the masks' data differ, so does the estimate
    assert np.max(np.abs(r.Err - one.Err)) < 0.02              # by a fraction of a pixel's quantisation
    with pytest.raises(ValueError, match="border_starts"):
        StrainRouteSettings(border_masks=True, border_starts=0)
    with pytest.raises(ValueError, match="border_starts: averages the masks' border data .* needs border_masks=True"):
        StrainRouteSettings(border_starts=8)
    assert type(StrainRouteSettings(border_masks=True, border_starts=8.0,
                                    border_correspondence="landmarks").border_starts) is int
    with pytest.raises(ValueError, match="border_starts: averages tracked landmarks .* needs border_correspondence="):
        StrainRouteSettings(border_masks=True, border_starts=8)          # the default places the border by the phase


def test_more_starts_warn_of_a_mended_mask_once(ring):
    import warnings
    ref, tracks, masks, _ = ring
    pinhole = masks.copy()
    assert masks[3, 16, 25] and masks[3, 15:18, 24:27].all()  # mid-wall, right of the cavity
    pinhole[3, 16, 25] = False                               # a pinhole in one frame's wall
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        border_masks_data(pinhole, ref, tracks.displacement.shape[0], mesh, PX, starts=4)
    mended = [w for w in seen if "masks[3]: not one ring" in str(w.message)]
    assert len(mended) == 1, [str(w.message) for w in seen]


def _true_node_motion(mesh):
    """(F, n_nodes, 2) px: the ring's exact displacement at the mesh's nodes."""
    X = mesh.nodes / PX
    d = X - CENTRE
    R = np.linalg.norm(d, axis=1)
    return np.array([((np.sqrt(R ** 2 - A) - R) / R)[:, None] * d for A in AREAS])


def test_guided_border_data_read_the_borders_true_motion_across_itself_at_the_guides_point(ring):
    """With the exact motion as guide, each border node's datum is its true normal displacement, to within the
    binary masks' quantisation; a guide off by half a pixel along or across the border changes the data by a small
    fraction of that (the masks, not the guide, say where the border is)."""
    from sfem_filters.cardiac.border_data import _node_normals, guided_border_data
    ref, tracks, masks, _ = ring
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    guide = _true_node_motion(mesh)
    g = guided_border_data(mesh, masks, guide, PX)
    n = _node_normals(mesh)[g.nodes]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    true = np.einsum("fkc,kc->fk", guide[:, g.nodes], n)
    err = g.y / PX - true
    assert g.y.shape == (len(AREAS), len(g.nodes)) and g.tracks is None and g.sd_tangent_px is None
    assert np.sqrt(np.mean(err ** 2)) < QUANTISATION_SD_PX
    endo = np.isin(g.nodes, lv_geometry(mesh).endo)
    assert abs(err[:, endo].mean()) < 0.1 and abs(err[:, ~endo].mean()) < 0.1          # no bias on either border
    assert np.abs(true).max() > 1.0                                      # the border moves by more than that
    t = np.column_stack([-n[:, 1], n[:, 0]])
    for direction in (t, n):                                             # half a pixel along, then across
        off = guide.copy()
        off[:, g.nodes] += 0.5 * direction
        moved = guided_border_data(mesh, masks, off, PX)
        assert np.sqrt(np.mean((moved.y - g.y) ** 2)) / PX < 0.1
    # one row per border node, on its normal; the sd the larger of the quantisation and the data's own floor
    assert g.H.shape == (len(g.nodes), mesh.n_dofs) and np.allclose(abs(g.H).sum(axis=1).A.ravel(),
                                                                     np.abs(n).sum(axis=1))
    assert np.allclose(np.sqrt(np.diagonal(g.R, axis1=1, axis2=2)) / PX, max(QUANTISATION_SD_PX, g.floor_px))
    with pytest.raises(ValueError, match=r"guide_px: expected the displacement of the mesh's"):
        guided_border_data(mesh, masks, guide[:, :-1], PX)
    with pytest.raises(ValueError, match="guide_px: expected a finite displacement"):
        guided_border_data(mesh, masks, np.where(np.arange(mesh.n_nodes)[None, :, None] == g.nodes[0], np.nan,
                                                     guide), PX)
    with pytest.raises(ValueError, match=r"masks: expected the reference and each frame's mask"):
        guided_border_data(mesh, masks[0], guide, PX)
    with pytest.raises(ValueError, match="starts: guided border data have no contour start"):
        border_masks_data(masks, ref, len(AREAS), mesh, PX, starts=2, guide_px=guide)


def test_the_route_places_the_border_by_the_phase_by_default_and_names_a_bad_choice(ring):
    ref, tracks, masks, err = ring
    cfg = StrainRouteSettings(element_px=2.0, border_masks=True, phase_noise_level="evidence",
                              process_profile="constant")                 # one process level: the border data alone
    assert cfg.border_correspondence == "phase"
    guided = dense_strain(tracks, ref, PX, cfg, masks=masks)
    landmarks = dense_strain(tracks, ref, PX, replace(cfg, border_correspondence="landmarks"), masks=masks)
    s = guided.settings
    assert s["border_correspondence"] == "phase" and s["border_landmarks"] is None
    assert s["border_rows"] == s["border_nodes"] > 0
    assert landmarks.settings["border_landmarks"] > 0
    # on a circle the landmarks do not slide, so both data are near the truth and the estimates near each other;
    # both pull the lagging phase estimate towards the true thickening
    alone = dense_strain(tracks, ref, PX, replace(cfg, border_masks=False, phase_noise_level="stated"))
    rmse = {k: float(np.sqrt(np.mean((r.Err - err) ** 2))) for k, r in (("alone", alone), ("guided", guided),
                                                                         ("landmarks", landmarks))}
    assert rmse["guided"] < 0.75 * rmse["alone"] and rmse["landmarks"] < 0.75 * rmse["alone"]
    assert np.sqrt(np.mean((guided.Err - landmarks.Err) ** 2)) < 0.25 * rmse["landmarks"]
    # the phase pass that places the border also gives the phase data's own level (no second pass)
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    assert s["phase_noise_scale"] == pytest.approx(phase_noise_level(mesh, tracks, PX, cfg), rel=1e-9)
    # with the process level chosen by evidence, the guide runs at the default level and the phase data's own level
    # is measured again at the chosen one
    chosen = dense_strain(tracks, ref, PX, replace(cfg, process_fraction=None), masks=masks)
    q = chosen.settings["process_fraction"]
    assert q != cfg.process_fraction
    assert chosen.settings["phase_noise_scale"] == pytest.approx(
        phase_noise_level(mesh, tracks, PX, replace(cfg, process_fraction=q)), rel=1e-9)
    with pytest.raises(ValueError, match="border_correspondence: expected one of"):
        StrainRouteSettings(border_masks=True, border_correspondence="bending")


def _unbiased_fusion():
    """Tracks without bias and exact masks on the ring: the reference, tracks, masks, mesh, fused settings with
    both levels by evidence, the phase data's own level and the masks' guided border data."""
    from sfem_filters.cardiac.dense_model import phase_only_pass
    ref, tracks, masks, _ = _ring(lag=0.0)
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    cfg = StrainRouteSettings(element_px=2.0, border_masks=True, phase_noise_level="evidence",
                              mask_noise_level="evidence")
    c, guide = phase_only_pass(mesh, tracks, PX, cfg, smooth=True)
    return ref, tracks, masks, mesh, cfg, c, border_masks_data(masks, ref, len(AREAS), mesh, PX, guide_px=guide)


def test_the_masks_level_by_evidence_gives_masks_drawn_worse_less_weight():
    """Tracks without bias, exact masks: the same masks' data with 0.5 px of independent noise added to every
    border datum (about four times the variance of a binary border's quantisation) get a variance factor several
    times larger from the evidence of the fused model than the masks as drawn (variance components)."""
    from sfem_filters.cardiac.dense_model import MASK_LEVELS, mask_noise_level_ml
    ref, tracks, masks, mesh, cfg, c, border = _unbiased_fusion()
    clean, table = mask_noise_level_ml(mesh, tracks, PX, cfg, border, c)
    rng = np.random.default_rng(1)
    noisy = replace(border, y=border.y + 0.5 * PX * rng.standard_normal(border.y.shape))
    worse, _ = mask_noise_level_ml(mesh, tracks, PX, cfg, noisy, c)
    assert set(table) <= set(MASK_LEVELS) and len(table) >= 3 and all(np.isfinite(v).all() for v in table.values())
    assert min(MASK_LEVELS) <= clean <= max(MASK_LEVELS) and worse > 4 * clean
    # the search walks until the best evaluated candidate has both neighbours evaluated (or is at the grid's end):
    # the same choice as evaluating every candidate, for an evidence with one maximum
    # the search scales the masks' block of one model: the same covariances as a model built with the scaled masks
    model, y, _, _ = build_dense_model(mesh, tracks, PX, cfg, border=border, phase_scale=c)
    rebuilt, y2, _, _ = build_dense_model(mesh, tracks, PX, cfg, border=replace(border, R=4.0 * border.R),
                                          phase_scale=c)
    scaled = model.with_block_noise(mesh.n_dofs, 4.0)
    assert np.allclose(y, y2) and all(np.allclose(scaled.R_at(t), rebuilt.R_at(t)) for t in (0, 3, len(AREAS) - 1))
    assert np.allclose(model.R_at(3), build_dense_model(mesh, tracks, PX, cfg, border=border, phase_scale=c)[0].R_at(3))
    with pytest.raises(ValueError, match="first: expected rows .* independent"):
        model.with_block_noise(mesh.n_dofs - 1, 2.0)
    each = {f: mask_noise_level_ml(mesh, tracks, PX, cfg, border, c, candidates=[f])[1][f][0] for f in MASK_LEVELS}
    best = max(each, key=each.get)
    assert best in table and table[best][0] == pytest.approx(each[best])
    k = MASK_LEVELS.index(best)
    assert MASK_LEVELS[max(k - 1, 0)] <= clean <= MASK_LEVELS[min(k + 1, len(MASK_LEVELS) - 1)]
    # the route reports the factor it used and the evidence of each candidate
    r = dense_strain(tracks, ref, PX, cfg, masks=masks)
    assert r.settings["mask_noise_scale"] == pytest.approx(clean, rel=1e-9)
    assert set(r.settings["mask_noise_evidence"]) == {f"{f:g}" for f in table}
    with pytest.raises(ValueError, match="candidates: expected at least one factor"):
        mask_noise_level_ml(mesh, tracks, PX, cfg, border, c, candidates=())
    with pytest.raises(TypeError, match="border: expected a BorderData"):
        mask_noise_level_ml(mesh, tracks, PX, cfg, None, c)
    with pytest.raises(ValueError, match="mask_noise_level: 'evidence' weighs the masks .* needs border_masks=True"):
        StrainRouteSettings(mask_noise_level="evidence")
    with pytest.raises(ValueError, match="mask_noise_level: expected one of"):
        StrainRouteSettings(border_masks=True, mask_noise_level="fitted")


@pytest.mark.parametrize("kind", ["gmsh", "pixels"])
def test_guided_border_data_are_zero_when_nothing_moves_on_either_mesh(ring, kind):
    """Masks that do not move and a guide of zero: every datum is zero, though the mesh's border lies off the
    mask's (a polygon's chords cut the curve; the node-per-pixel mesh's border is half a pixel inside it)."""
    from sfem_filters.cardiac.border_data import guided_border_data
    ref = ring[0]
    mesh = reference_mesh(ref, PX, kind, 2.0)
    g = guided_border_data(mesh, np.repeat(ref[None], 4, axis=0), np.zeros((3, mesh.n_nodes, 2)), PX)
    assert g.y.shape[1] == len(g.nodes) > 20 and np.max(np.abs(g.y)) / PX < 1e-9


def _cut(mask, width_px=3.0):
    """``mask`` with a radial gap of ``width_px`` rows through its wall on the +x side: no cavity, not mendable."""
    yy, xx = np.mgrid[0:mask.shape[0], 0:mask.shape[1]]
    return mask & ~((np.abs(yy - CENTRE[1]) <= width_px / 2) & (xx > CENTRE[0]))


def test_a_frame_whose_mask_cannot_be_read_leaves_only_its_own_border_rows_out(ring):
    """Guided border data read each frame's mask on their own: a frame whose mask is cut through (no cavity) has
    missing data (NaN), with a warning naming it, and every other frame's are those of the intact masks; the route
    then fuses the other frames' borders, and its radial strain stays near the intact masks' estimate, nearer than
    the phase alone (which leaving every frame out, as before, gave)."""
    from sfem_filters.cardiac.border_data import guided_border_data
    ref, tracks, masks, err = ring
    mesh = reference_mesh(ref, PX, "gmsh", 2.0)
    guide = _true_node_motion(mesh)
    whole = guided_border_data(mesh, masks, guide, PX)
    cut = masks.copy()
    cut[4] = _cut(cut[4])
    with pytest.warns(RuntimeWarning, match=r"masks: the mask\(s\) of frame\(s\) \[3\] \(masks\[4\]\) cannot be made one ring.*"
                                            r"left out \(those frames observe the phase alone\)"):
        part = guided_border_data(mesh, cut, guide, PX)
    assert np.all(np.isnan(part.y[3])) and np.all(np.isfinite(np.delete(part.y, 3, axis=0)))
    assert np.allclose(np.delete(part.y, 3, axis=0), np.delete(whole.y, 3, axis=0))
    assert np.all(np.isfinite(part.R))
    every = masks.copy()
    every[1:] = [_cut(m) for m in masks[1:]]
    with pytest.raises(ValueError, match="masks: expected at least one frame's mask that can be made one ring"):
        guided_border_data(mesh, every, guide, PX)
    with pytest.raises(ValueError, match=r"masks\[0\]: expected a ring"):
        guided_border_data(mesh, np.concatenate([_cut(masks[0])[None], masks[1:]]), guide, PX)
    # through the route: the other frames' borders still pull the lagging endocardium back
    cfg = StrainRouteSettings(element_px=2.0, border_masks=True, phase_noise_level="evidence",
                              process_profile="constant")           # the phase data at their own level: masks count
    fused = dense_strain(tracks, ref, PX, cfg, masks=masks)
    with pytest.warns(RuntimeWarning, match=r"frame\(s\) \[3\]"):
        gapped = dense_strain(tracks, ref, PX, cfg, masks=cut)
    alone = dense_strain(tracks, ref, PX, replace(cfg, border_masks=False, phase_noise_level="stated"))
    rmse = {k: float(np.sqrt(np.mean((r.Err - err) ** 2))) for k, r in (("fused", fused), ("gapped", gapped),
                                                                         ("alone", alone))}
    assert np.all(np.isfinite(gapped.Err)) and np.all(np.isfinite(gapped.Err_sd)), rmse
    assert rmse["gapped"] < 0.75 * rmse["alone"] and rmse["gapped"] < 1.25 * rmse["fused"]


def test_masks_that_disagree_with_the_phase_beyond_every_level_are_named():
    """Border data with 6 px of noise (twenty times a binary border's quantisation, far beyond the largest
    factor on their variance): the evidence rises to the grid's end, the least weight offered is taken, and a
    warning says that the masks may not belong to these images; masks as drawn give no such warning."""
    from sfem_filters.cardiac.dense_model import MASK_LEVELS, mask_noise_level_ml
    ref, tracks, masks, mesh, cfg, c, border = _unbiased_fusion()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mask_noise_level_ml(mesh, tracks, PX, cfg, border, c)
    rng = np.random.default_rng(2)
    wild = replace(border, y=border.y + 6.0 * PX * rng.standard_normal(border.y.shape))
    with pytest.warns(RuntimeWarning, match=r"masks: their evidence still rises at the largest factor .*--no-masks"):
        f, table = mask_noise_level_ml(mesh, tracks, PX, cfg, wild, c)
    assert max(table) == max(MASK_LEVELS) and f == pytest.approx(max(MASK_LEVELS))


def test_a_reference_mask_thicker_than_every_frames_is_named_before_the_masks_join_the_phase(ring):
    """Frames' masks a pixel thinner than the reference (drawn by another hand): the route warns, naming both
    areas, before any pass (before its first filter pass's progress line); the ring's own masks (their areas vary by
    the pixels' quantisation) do not. A frame whose mask cannot be read (a filled disc, left out of the data) does
    not hide it, and frames given alone, (F, H, W), are told how the message indexes them."""
    ref, tracks, masks, err = ring
    assert reference_mask_mismatch(masks) is None
    thin = masks.copy()
    thin[1:] = [binary_erosion(m) for m in masks[1:]]
    cfg = StrainRouteSettings(element_px=2.0, border_masks=True, phase_noise_level="evidence",
                              process_profile="constant")
    warned_at = []
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        r = dense_strain(tracks, ref, PX, cfg, masks=thin,
                         progress=lambda m: warned_at.append((m, sum("the reference" in str(w.message) for w in seen))))
    hits = [str(w.message) for w in seen if "the reference" in str(w.message)]
    assert len(hits) == 1 and re.match(rf"^masks\[0\] \(the reference\) holds {ref.sum()} pixels and masks\[1\] "
                                       rf"\(the first frame\) {thin[1].sum()}.*the masks' borders join the phase",
                                       hits[0])
    passes = [n for m, n in warned_at if "the phase data alone" in m]
    assert passes and passes[0] == 1                        # warned before the first filter pass began
    assert r.settings["reference_mask_mismatch"].startswith("masks[0] (the reference) holds")   # kept in the JSON
    disc = thin.copy()
    disc[3] = np.hypot(*(np.mgrid[0:SIZE, 0:SIZE] - np.array(CENTRE)[::-1, None, None])) <= R_OUT + 4
    with pytest.warns(RuntimeWarning, match=r"^masks\[0\] \(the reference\).*join the phase data \(indices of "
                                            r"the masks with reference_mask prepended"):
        dense_strain(tracks, ref, PX, cfg, masks=disc[1:])
