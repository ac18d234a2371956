"""From images to image-derived data: readers, segmentation, contours, shape tracking, phase contrast.

Knows neither the finite elements nor the filters; units are pixels (x = column, y = row)
unless a docstring says otherwise, velocities in m/s. Section 2.6 of Shi & Liu (2003): borders
are tracked by bending-energy matching with a confidence per match (Eqs. 35-37), phase-contrast
velocities get their confidence from the local phase coherence (Eqs. 38-39).

>>> import numpy as np
>>> from sfem_filters.imaging import bending_energy, local_phase_coherence, mask_borders, track_masks
>>> yy, xx = np.mgrid[0:32, 0:32]
>>> r = np.hypot(xx - 15.5, yy - 15.5)
>>> ring = (r >= 6) & (r <= 11)                                  # a myocardium-like ring
>>> b = mask_borders(ring, n_endo=32, n_epi=48)                   # ordered endo / epi contours
>>> b.endo.shape, b.epi.shape
((32, 2), (48, 2))
>>> tracks = track_masks(np.stack([ring, ring, ring]))            # Eqs. 35-37 frame to frame
>>> float(np.abs(tracks.displacement).max()) < 1e-9               # a still ring does not move
True
>>> round(float(bending_energy(0.1, 0.3)), 12)                     # Eq. 35
0.02
>>> float(local_phase_coherence(np.zeros((5, 5)))[2, 2])          # Eqs. 38-39: smooth phase
1.0

Modules: :mod:`~sfem_filters.imaging.readers` (npz/npy, DICOM, NIfTI),
:mod:`~sfem_filters.imaging.dense_io` (DENSE-Sim case folders, DENSE DICOM series and folders),
:mod:`~sfem_filters.imaging.dense` (phase to Lagrangian displacement),
:mod:`~sfem_filters.imaging.segmentation` (morphological Chan-Vese),
:mod:`~sfem_filters.imaging.contours`, :mod:`~sfem_filters.imaging.tracking`,
:mod:`~sfem_filters.imaging.confidence` (bending energy, goodness, uniqueness, LPC, weights),
:mod:`~sfem_filters.imaging.phase_contrast` (velocity sampling and error model),
:mod:`~sfem_filters.imaging.spline_strain` (thin-plate-spline strain through tracked points, the
physics-free baseline), :mod:`~sfem_filters.imaging.strain_report` (peaks, ground-truth curves and the tidy CSV of a strain report).
"""
from .confidence import (bending_energy, goodness_uniqueness, local_phase_coherence, match_confidence,
                         segment_bending_energy, velocity_coherence, weighted_std)
from .conventional import ConventionalStrain, conventional_analysis, conventional_from_displacement
from .dense import (DenseCase, LagrangianDisplacement, add_complex_noise, make_dense_case, phase_to_displacement,
                    read_dense_dicom, read_dense_sim, reference_points, tracks_on_pixel_grid, truth_at_points)
from .dense_io import dense_masks, dense_sim_grid, read_dense_dicom_folder
from .strain import (StrainEstimate, StrainField, curve_peak, global_curve, green_strain, mask_centre, segment_curves,
                     segment_labels,
                     strain_on_grid)
from .spline_strain import SplineStrain, spline_strain, tps_gradient_operators
from .strain_report import peaks, spline_block, strain_csv, truth_block, with_peaks
from .contours import Borders, check_myocardium_mask, curvature, mask_borders, midwall_pixels, pixel_depth, \
    reference_mask_mismatch, repair_myocardium_mask, resample_closed
from .phase_contrast import VelocityData, sample_bilinear, sample_velocity, synthetic_phase_contrast
from .readers import ImageSeries, make_image_series, read_images
from .segmentation import dice, segment_sequence
from .tracking import BoundaryTracks, TrackingOptions, track_borders, track_masks

from .dense import background_signal, interpolation_variance_factor, psf_samples, psf_sigma_px
from .strain import displacement_gradient
from .contours import closest_on_polyline
__all__ = ["bending_energy", "segment_bending_energy", "goodness_uniqueness", "match_confidence",
           "local_phase_coherence", "velocity_coherence", "weighted_std", "Borders", "check_myocardium_mask",
           "repair_myocardium_mask", "reference_mask_mismatch", "curvature", "mask_borders", "resample_closed",
           "pixel_depth", "midwall_pixels",
           "VelocityData", "sample_bilinear", "sample_velocity",
           "synthetic_phase_contrast", "ImageSeries", "make_image_series", "read_images", "dice",
           "segment_sequence", "BoundaryTracks", "TrackingOptions", "track_borders", "track_masks",
           "DenseCase", "LagrangianDisplacement", "make_dense_case", "read_dense_sim", "read_dense_dicom",
           "read_dense_dicom_folder", "dense_masks", "dense_sim_grid", "tracks_on_pixel_grid",
           "add_complex_noise", "phase_to_displacement", "reference_points", "truth_at_points", "StrainField",
           "strain_on_grid", "green_strain", "mask_centre", "segment_labels", "global_curve", "segment_curves",
           "curve_peak", "ConventionalStrain", "conventional_analysis", "conventional_from_displacement",
           "peaks", "truth_block", "spline_block", "with_peaks", "strain_csv", "SplineStrain", "spline_strain",
           "StrainEstimate",
           "tps_gradient_operators",
           "background_signal", "psf_sigma_px", "displacement_gradient",
           "closest_on_polyline", "psf_samples", "interpolation_variance_factor"]
