"""The DENSE route's resolution-aware observation operator: a thickening ring imaged through a known point spread.

Ground truth from an analytic deformation (an area-preserving inward thickening, exact Green strain)
rendered by our own generator as complex DENSE signal on a fine grid, blurred by the Gaussian point
spread of a stated acquired resolution and sampled at the pixel centres, with a static lit background.
"""
from dataclasses import replace

import numpy as np
import pytest
from scipy import ndimage

pytest.importorskip("gmsh", reason="gmsh (the optional mesher, GPL-2.0-or-later) is not installed")

from sfem_filters.cardiac.strain_route import (StrainRouteSettings, dense_case_strain, dense_strain,  # noqa: E402
                                               image_settings, masks_move, route_settings)
from sfem_filters.imaging.dense import (background_signal, make_dense_case, phase_to_displacement,  # noqa: E402
                                        psf_sigma_px)

KE, PX = 0.1, 1.75                          # cycles/mm, mm
RAD_PER_PX = 2 * np.pi * KE * PX
R_IN, R_OUT, CENTRE, SHAPE = 8.0, 12.5, (21.3, 20.6), (42, 42)
AREAS = 24.0 * np.sin(np.pi * np.arange(1, 10) / 10)    # px^2: the wall thickens to mid-cycle and relaxes
BACKGROUND = 0.3                            # static background's signal over the tissue's
SUB = 5                                     # fine samples per pixel (each axis)


def render_blurred_ring(resolution_px, areas=AREAS):
    """Frames of a ring thickening inwards, r^2 = R^2 - A_t (area preserving), as wrapped phase of a complex
    signal blurred by the Gaussian PSF of ``resolution_px``; and the exact Green-Lagrange Err (F, H, W)."""
    c = np.asarray(CENTRE)
    fine = (np.mgrid[0:SHAPE[0] * SUB, 0:SHAPE[1] * SUB].astype(float) - (SUB - 1) / 2) / SUB    # pixel units
    fy, fx = fine
    rf = np.hypot(fx - c[0], fy - c[1])
    yy, xx = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(float)
    r_px = np.hypot(xx - c[0], yy - c[1])
    ref = (r_px >= R_IN) & (r_px <= R_OUT)
    sd_fine = psf_sigma_px(resolution_px) * SUB
    phases, mags, masks, err = [], [], [ref], []
    for A in areas:
        R = np.sqrt(rf ** 2 + A)                                 # reference radius of what is now at rf
        tissue = (R >= R_IN) & (R <= R_OUT)
        scale = 1 - R / np.maximum(rf, 1e-9)
        u = np.stack([(fx - c[0]) * scale, (fy - c[1]) * scale], axis=-1)
        sig = np.where(tissue, 1.0, BACKGROUND)
        u = np.where(tissue[..., None], u, 0.0)                  # the background is static
        enc = []
        for j in range(2):
            z = sig * np.exp(1j * RAD_PER_PX * u[..., j])
            if sd_fine > 0:
                z = ndimage.gaussian_filter(z.real, sd_fine) + 1j * ndimage.gaussian_filter(z.imag, sd_fine)
            enc.append(z[SUB // 2::SUB, SUB // 2::SUB])
        phases.append([np.angle(e) for e in enc])
        mags.append(np.abs(enc[0]))
        Rp = np.sqrt(r_px ** 2 + A)
        masks.append((Rp >= R_IN) & (Rp <= R_OUT))
        rr = np.sqrt(np.maximum(r_px ** 2 - A, 1e-9))            # current radius of the reference pixel
        err.append(np.where(ref, 0.5 * ((r_px / rr) ** 2 - 1), np.nan))
    case = make_dense_case(np.transpose(np.array(phases), (1, 0, 2, 3)), np.array(mags), np.stack(masks), PX, KE,
                           0.015 * (1 + np.arange(len(areas))), resolution_px=resolution_px)
    return case, np.array(err)


def _peak_bias(case, err, resolution_px, background):
    """Mean Err error (fraction) at the peak frame, and the true mean there. Process noise at the noise floor:
    on noise-free images the default 0.1 of the floor leaves the smoother's own dynamics to overshoot a
    deblurred peak (measured: +15 points at the peak), which is not what this test is about."""
    tracks = phase_to_displacement(case)
    truth = err[:, case.reference_mask]
    r = dense_strain(tracks, case.reference_mask, case.pixel_size_m,
                     StrainRouteSettings(resolution_px=resolution_px, discrepancy=False, process_fraction=1.0),
                     background=background)
    peak = int(np.argmax(AREAS))
    return float(np.mean(r.Err[peak] - truth[peak])), float(np.mean(truth[peak]))


def test_the_operator_recovers_the_blurred_rings_radial_strain_with_less_bias():
    sharp, err = render_blurred_ring(1.0)
    blurred, _ = render_blurred_ring(2.5)
    own, truth_peak = _peak_bias(sharp, err, 1.0, None)          # the route's own bias on unblurred images
    point, _ = _peak_bias(blurred, err, 1.0, None)
    operator, _ = _peak_bias(blurred, err, blurred.resolution_px, background_signal(blurred))
    dark, _ = _peak_bias(blurred, err, blurred.resolution_px, None)
    # the blur flattens the radial strain the point observation reports ...
    assert point < own - 0.05 * truth_peak
    # ... the operator takes it back: less bias than the point observation, by half at least
    assert abs(operator) < 0.5 * abs(point)
    # and the lit background is part of it: the operator that takes it for dark overcorrects
    assert abs(dark) > 2 * abs(operator)


def test_the_background_signal_is_read_where_the_tissues_blur_has_faded():
    case, _ = render_blurred_ring(2.5)
    b = np.abs(background_signal(case).signal[..., 0])
    far = ~ndimage.binary_dilation(case.frame_masks[-1], iterations=4)
    assert np.allclose(np.median(b[-1][far]), BACKGROUND, atol=0.05)


# ------------------------------------------------------------------ the route's default for images
def test_image_settings_take_the_acquisition_and_fuse_masks_only_when_they_move():
    case, _ = render_blurred_ring(2.5)
    cfg = image_settings(case)
    assert cfg.resolution_px == case.resolution_px == 2.5
    assert cfg.border_masks and cfg.phase_noise_level == cfg.mask_noise_level == "evidence"
    assert cfg.process_profile == "data" and cfg.border_correspondence == "phase"
    alone = image_settings(case, border_masks=False)
    assert not alone.border_masks and alone.phase_noise_level == alone.mask_noise_level == "stated"
    assert image_settings(case, resolution_px=1.0).resolution_px == 1.0
    with pytest.raises(TypeError, match="overrides: expected StrainRouteSettings fields, got \\['resolution'\\]"):
        image_settings(case, resolution=1.0)
    still = replace(case, masks=np.repeat(case.masks[:1], case.masks.shape[0], axis=0))   # one mask for all frames
    assert masks_move(case.masks) and not masks_move(still.masks)
    assert not image_settings(still).border_masks and image_settings(still).phase_noise_level == "stated"
    plain = route_settings()                                          # tracks alone: no acquisition, no masks
    assert plain.resolution_px == 1.0 and not plain.border_masks and plain.phase_noise_level == "stated"
    assert route_settings(2.0, True) == replace(cfg, resolution_px=2.0)
    forced = image_settings(still, border_masks=True)                 # fused on request: at the evidence level
    assert forced.border_masks and forced.phase_noise_level == forced.mask_noise_level == "evidence"
    with pytest.raises(TypeError, match="case: expected a DenseCase"):
        image_settings(case.masks)
    # the node-per-pixel mesh ends half a pixel inside the mask: the point spread would read that as background
    with pytest.raises(ValueError, match="resolution_px: the point spread's observation needs .*mesh='gmsh'"):
        image_settings(case, mesh="pixels")
    assert image_settings(case, mesh="pixels", resolution_px=1.0).mesh == "pixels"
    with pytest.raises(ValueError, match="masks"):
        masks_move(case.masks[0])


def test_dense_case_strain_is_dense_strain_with_the_images_background_and_masks():
    case, _ = render_blurred_ring(2.5, areas=AREAS[:5])
    tracks = phase_to_displacement(case)
    cfg = image_settings(case, element_px=2.0)
    a = dense_case_strain(case, cfg, tracks=tracks)
    b = dense_strain(tracks, case.reference_mask, case.pixel_size_m, cfg, background=background_signal(case),
                     masks=case.masks)
    assert np.array_equal(a.Err, b.Err) and np.array_equal(a.Err_sd, b.Err_sd)
    assert a.settings["border_masks"] and a.settings["resolution_px"] == 2.5


def test_the_default_for_images_brings_the_blurred_rings_radial_peak_closer_than_the_phase_alone():
    """The images' default (point spread, masks at the evidence level, profile) against the earlier default (the
    phase alone at the pixel centres, one process level) on a ring imaged through a known point spread."""
    case, err = render_blurred_ring(2.5)
    tracks = phase_to_displacement(case)
    truth = err[:, case.reference_mask]
    peak = int(np.argmax(AREAS))
    bias = {}
    for name, cfg in {"images": image_settings(case),
                      "earlier": image_settings(case, resolution_px=1.0, border_masks=False,
                                                process_profile="constant")}.items():
        r = dense_case_strain(case, cfg, tracks=tracks)
        bias[name] = float(np.mean(r.Err[peak] - truth[peak]))
    assert bias["earlier"] < -0.1 * np.mean(truth[peak])           # the blur flattens the phase alone's peak
    assert abs(bias["images"]) < 0.5 * abs(bias["earlier"])
