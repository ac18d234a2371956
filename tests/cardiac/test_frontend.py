"""Images to observations in the filter: velocity weighting by LPC, fusion of tracked borders and
velocity in the joint EKF, and the observe command."""
import os

import numpy as np
import pytest

from sfem_filters.cardiac import annulus, frontend, measured
from sfem_filters.cardiac.sequence import example_path, load_sequence, make_sequence
from sfem_filters.cli import main
from sfem_filters.filtering import cyclic_estimate
from sfem_filters.imaging.confidence import velocity_coherence
from sfem_filters.imaging.contours import pixel_depth
from sfem_filters.imaging.phase_contrast import (
    sample_velocity,
    synthetic_phase_contrast,
)
from sfem_filters.imaging.tracking import TrackingOptions, track_masks


def _synthetic_pc(seed=1, n_frames=12, noise_mid=0.05, noise_border=1.0):
    seq, truth = annulus.annulus_sequence(effect="active_polar", seed=seed, return_truth=True, beta=0.03,
                                            n_frames=n_frames)
    H, W = seq.reference_mask.shape
    s = seq.pixel_spacing
    c = np.rint(seq.points).astype(int)
    vimg = np.zeros((seq.n_frames, H, W, 2))
    vimg[:, c[:, 1], c[:, 0]] = truth["velocity"] * s
    vmax = float(np.abs(vimg).max())
    venc = 2.0 * vmax
    depth = pixel_depth(seq.reference_mask)
    pc = synthetic_phase_contrast(vimg, seq.reference_mask, venc, noise_mid * vmax, noise_border * vmax, depth, seed)
    return seq, truth, pc, venc, vmax, depth


def test_lpc_high_at_midwall_low_at_borders_and_outside():
    seq, truth, pc, venc, vmax, depth = _synthetic_pc()
    lpc = velocity_coherence(pc, venc)
    m = seq.reference_mask
    mid = lpc[:, m & (np.abs(depth - 0.5) <= 0.15)].mean()
    border = lpc[:, m & (np.abs(depth - 0.5) >= 0.3)].mean()
    outside = lpc[:, ~m].mean()
    assert mid > 0.8 and mid > border + 0.2 and border > outside


def test_lpc_weighting_lowers_the_filters_velocity_error():
    """(1 - LPC)-weighted R against a uniform R (every velocity at the median of the weighted
    standard deviations: one nominal noise level for the acquisition, as without confidences):
    the filter's velocity estimate is closer to the truth with the
    weighting, and either is closer than no velocity data at all."""
    seq, truth, pc, venc, vmax, depth = _synthetic_pc(noise_mid=0.05, noise_border=1.0)
    vel = sample_velocity(pc, seq.points, venc, seq.pixel_spacing, floor=0.01 * vmax)
    errors = {}
    for weighting in ("lpc", "uniform", "none"):
        setup = measured.prepare(seq, 8)
        mid = np.arange(seq.n_points)          # velocity at every tissue pixel, borders included
        if weighting != "none":
            setup.velocity_points = mid
            setup.velocity = vel.velocity[:, mid]
            sd = vel.sigma[:, mid]
            setup.velocity_sigma = sd if weighting == "lpc" else np.full_like(sd, np.median(sd))
        model, y = measured.build_model(setup, (), "penalty", "none", beta=0.03)
        res = cyclic_estimate(model, y, max_loops=1, progress=False)
        V = model.velocities(res.states).reshape(seq.n_frames, -1, 2) / seq.pixel_spacing
        errors[weighting] = np.sqrt(np.mean((V[1:, mid] - truth["velocity"][1:, mid]) ** 2))
    print(errors)
    assert errors["lpc"] < 0.95 * errors["uniform"] and errors["uniform"] < errors["none"], errors


# --------------------------------------------------------- fusion of borders and velocity
def test_velocity_fusion_beats_borders_alone_on_heldout_points():
    """Known answer: masks drawn from the true motion, tracked; velocities with border noise."""
    seq, truth, pc, venc, vmax, depth = _synthetic_pc(seed=2, n_frames=12)
    masks = annulus.deformed_masks(seq, truth["displacement"])
    tracks = track_masks(masks, TrackingOptions(window=4, regularisation=4.0))
    vel = sample_velocity(pc, seq.points, venc, seq.pixel_spacing, floor=0.01 * vmax)
    reference = make_sequence(seq.points, truth["displacement"], frame_interval=seq.frame_interval,
                              pixel_spacing=seq.pixel_spacing, reference_mask=seq.reference_mask)
    out = frontend.compare_fusion(reference, tracks, vel, max_loops=1, beta=0.03, estimator="cyclic")
    a, b = out["borders"], out["borders+velocity"]
    print({k: round(v["heldout_rmse_px"], 3) for k, v in out.items()})
    assert a["n_heldout"] == b["n_heldout"] and b["n_velocity_points"] > 0
    assert b["heldout_rmse_px"] < 0.85 * a["heldout_rmse_px"], out


# ------------------------------------------------------------------------- observe command
def test_observe_command_writes_a_loadable_sequence_and_figures(tmp_path):
    seq, truth, pc, venc, vmax, depth = _synthetic_pc(n_frames=6)
    masks = annulus.deformed_masks(seq, truth["displacement"])
    src = tmp_path / "images.npz"
    np.savez(src, masks=masks, velocity=pc, venc=venc, pixel_spacing=seq.pixel_spacing,
             frame_interval=seq.frame_interval)
    out = tmp_path / "obs" / "seq.npz"
    figs = tmp_path / "figs"
    assert main(["observe", str(src), "--out", str(out), "--figures", str(figs)]) == 0
    s = load_sequence(out)
    border = s.point_kind < 2
    assert np.all(np.isfinite(s.displacement[:, border])) and np.all(np.isnan(s.displacement[:, ~border]))
    assert np.all(np.isfinite(s.velocity[:, ~border])) and np.all(np.isnan(s.velocity[:, border]))
    assert np.all((s.confidence[:, border] >= 0) & (s.confidence[:, border] <= 1))
    assert np.all(s.velocity_sigma[:, ~border] > 0)
    assert sorted(os.listdir(figs)) == ["tracked_contours.png", "velocity_lpc.png"]


@pytest.mark.needs_data("subject_a")
def test_observe_on_masks_alone_writes_border_points_that_load_with_their_mask(tmp_path):
    """Without velocity images every point is a border point, on the half-pixel boundary of the
    mask: the sequence must still load with its reference mask (the shipped slice's masks)."""
    out = tmp_path / "seq.npz"
    assert main(["observe", str(example_path()), "--out", str(out)]) == 0
    s = load_sequence(out)
    assert s.reference_mask is not None and np.all(s.point_kind < 2)
    c, r = np.round(s.points).astype(int).T
    assert 0.2 < np.mean(s.reference_mask[r, c]) < 0.8      # many of them round off the tissue itself


def test_observe_command_user_errors_exit_2(tmp_path, capsys):
    assert main(["observe", str(tmp_path / "nope.npz"), "--out", str(tmp_path / "o.npz")]) == 2
    p = tmp_path / "empty.npz"
    np.savez(p, masks=np.zeros((3, 20, 20), bool))
    assert main(["observe", str(p), "--out", str(tmp_path / "o.npz")]) == 2
    err = capsys.readouterr().err
    assert "masks[0]: expected some tissue" in err and "Traceback" not in err
