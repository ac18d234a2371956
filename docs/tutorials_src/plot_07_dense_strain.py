"""
Strain from DENSE images, with its uncertainty
==============================================

A case of DENSE-Sim (Barbaroux et al., *JCMR* 2025; MIT licence; the data set
``"dense_sim/phantom_subject_1"`` of :mod:`sfem_filters.datasets`): cine DENSE images of an annular
phantom deformed by a kinematic model that is not ours, with a ground-truth Green-Lagrange strain
per pixel that nobody here wrote. Complex Gaussian noise is added at SNR 30, as the validation page
:doc:`../validation/strain_dense_sim` does; the phase becomes the Lagrangian displacement of every
reference pixel; the DENSE route turns it into Green-Lagrange strain with its sd and 95% bands, and
the conventional analysis (finite differences of the same tracks, smoothed by a Gaussian of 1 px)
runs beside it.

The route's default for images (:func:`sfem_filters.cardiac.image_settings`) observes the phase
through the acquisition's point spread, fuses every frame's myocardium mask with it and lets the
process noise follow the data's motion; the validation page measures what each part brings.

*Setting.* Quick: the first 16 frames (the wall thickens through them; a walk through the route, not
the numbers of the validation page). Full:
``sfem-filters strain CASE_DIR --json strain.json --snr 30 --figures strain/`` (all 40 frames, with
the spline beside and the figures of the report), or here ``SFEM_DOCS_QUICK=0``.

The case is not shipped with the package: it is read from the data directory
``$SFEM_FILTERS_DATA`` or the download cache, and otherwise downloaded once from its original
repository (with its licence).
"""

# %%
# The images, noise and tracks
# ----------------------------
import os
import warnings
from dataclasses import replace

import matplotlib.pyplot as plt
import numpy as np

from sfem_filters import datasets
from sfem_filters.benchmark import score_strain
from sfem_filters.cardiac import dense_case_strain, image_settings
from sfem_filters.imaging import (add_complex_noise, conventional_analysis, phase_to_displacement, read_dense_sim,
                                  truth_at_points)
from sfem_filters.imaging.strain import N_SEGMENTS, segment_curves

QUICK = os.environ.get("SFEM_DOCS_QUICK", "1") != "0"
# the smoother's consistency monitor warns where systole's innovations run high; the bands below
# carry the noise level the innovations show (the route's maximum-likelihood noise scale)
warnings.filterwarnings("ignore", message="filter inconsistent")

case = read_dense_sim(datasets.dataset_path("dense_sim/phantom_subject_1", download=True))
if QUICK:
    F = 16
    case = replace(case, phases=case.phases[:, :F], magnitude=case.magnitude[:F], masks=case.masks[:F + 1],
                   frame_times_s=case.frame_times_s[:F], truth_ecc=case.truth_ecc[:F], truth_err=case.truth_err[:F])
noisy = add_complex_noise(case, snr=30.0, seed=0)
tracks = phase_to_displacement(noisy)
print(f"{len(tracks.points)} reference pixels, {noisy.n_frames} frames, acquired resolution "
      f"{noisy.resolution_px:.2f} px, untracked (frame, pixel) pairs: {tracks.n_untracked}")

# %%
# The DENSE route
# ---------------
# ``image_settings`` reads what the images carry beyond the tracks: the acquired resolution and
# whether the masks move. Any field of :class:`~sfem_filters.cardiac.StrainRouteSettings` can be
# overridden (``image_settings(noisy, border_masks=False)`` for the phase alone).
settings = image_settings(noisy)
print(f"resolution {settings.resolution_px:.2f} px, masks fused: {settings.border_masks} "
      f"(phase level: {settings.phase_noise_level}), process noise: {settings.process_profile}")
ours = dense_case_strain(noisy, settings, tracks=tracks)
conv = conventional_analysis(noisy, sigma=1.0, tracks=tracks)
t_ecc, t_err = truth_at_points(case)
t_ms = 1e3 * ours.frame_times_s
print(f"{ours.settings['n_nodes']} nodes; {ours.seconds:.0f} s; ML noise scale {ours.settings['noise_scale_ml']:.2f}")

# %%
# Global curves against the truth
# -------------------------------
# The band is the 95% band of the linearised posterior, widened by the noise level the
# innovations show and by the excess error the data reveal (the module
# :mod:`sfem_filters.cardiac.strain_route`, step 6).
fig, axes = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")
for ax, q, truth, c in zip(axes, ("Ecc", "Err"), (t_ecc, t_err), (conv.global_Ecc, conv.global_Err)):
    g = ours.global_curves
    ax.fill_between(t_ms, 100 * g[f"{q}_lo"], 100 * g[f"{q}_hi"], color="C0", alpha=0.25, label="ours, 95% band")
    ax.plot(t_ms, 100 * g[q], color="C0", label="ours (DENSE route)")
    ax.plot(t_ms, 100 * c, color="C1", ls="--", label="conventional, sigma 1 px")
    ax.plot(t_ms, 100 * np.nanmean(truth, axis=1), color="k", lw=1.5, label="DENSE-Sim truth")
    ax.set_xlabel("time after encoding [ms]")
    ax.set_ylabel(f"global {q} [%]")
axes[0].legend(loc="lower left")
plt.show()

# %%
# Radial strain per segment
# -------------------------
# Six 60-degree segments from the image's +x axis towards +y about the reference myocardium's
# centre of mass. The conventional analysis smooths across a wall a few pixels thick, which flattens radial
# strain most at its peak, later in the cycle than these frames (the validation page measures it over
# the whole cycle); the band says how sure the route is in each segment and frame.
labels = ours.labels
truth_seg = segment_curves(t_err, labels)
fig, axes = plt.subplots(2, 3, figsize=(12, 6), layout="constrained", sharex=True, sharey=True)
s = ours.segment_curves
for k, ax in enumerate(axes.flat):
    ax.fill_between(t_ms, 100 * s["Err_lo"][k], 100 * s["Err_hi"][k], color="C0", alpha=0.25)
    ax.plot(t_ms, 100 * s["Err"][k], color="C0")
    ax.plot(t_ms, 100 * conv.segments_Err[k], color="C1", ls="--")
    ax.plot(t_ms, 100 * truth_seg[k], color="k", lw=1.5)
    ax.set_title(f"segment {k + 1}: {60 * k}-{60 * (k + 1)} deg", fontsize=10)
for ax in axes[1]:
    ax.set_xlabel("time after encoding [ms]")
for ax in axes[:, 0]:
    ax.set_ylabel("Err [%]")
plt.show()

# %%
# How close, and how sure
# -----------------------
# :func:`sfem_filters.benchmark.score_strain` scores both against the truth as the validation page
# does: pixel RMSE, peak errors (percentage points) and the fraction of segment-frames whose true
# segment mean lies inside our band.
mine = score_strain(ours.Ecc, ours.Err, t_ecc, t_err, ours.points, ours.centre, start_deg=ours.start_deg,
                    ecc_band=ours.band("Ecc"), err_band=ours.band("Err"))
theirs = score_strain(conv.strain.Ecc, conv.strain.Err, t_ecc, t_err, conv.strain.points, conv.strain.centre)
for name, sc in (("ours", mine), ("conventional, sigma 1 px", theirs)):
    print(f"{name:>26}: pixel RMSE Ecc {sc.pixel_rmse_Ecc:5.2f}, Err {sc.pixel_rmse_Err:5.2f}; global peak error "
          f"Ecc {sc.global_peak_error_Ecc:+.2f}, Err {sc.global_peak_error_Err:+.2f}; mean segment peak error Err "
          f"{sc.segment_peak_error_Err_mean:.2f}")
print(f"our segment bands cover the truth in {mine.coverage_pct_Ecc:.0f}% (Ecc) and {mine.coverage_pct_Err:.0f}% (Err) "
      f"of the {N_SEGMENTS} x {ours.Ecc.shape[0]} segment-frames")
